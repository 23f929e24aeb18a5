"""Small ROS bags for tests, written with rosbags' own writers (ROS 1, ROS 2 sqlite3 and MCAP) from
a synthetic box room: a camera moving slowly toward the far wall, its depth image, a 2D LiDAR scan
simulated from that depth with a known mount, CameraInfo and /tf_static."""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.spatial.transform import Rotation

from explorer.scan import lidar_model, simulate_ranges
from explorer.data.synthetic import intrinsics

T0 = 1_700_000_000          # seconds: the first image's stamp
PERIOD = 0.1                # seconds between images
MOUNT = {"fov": 100, "resolution": 1.0, "range_min": 0.05, "range_max": 8.0, "height": 0.05, "tilt": 2.0}
CAMERA, LASER, BASE = "camera_optical", "laser", "base_link"
#: base_link -> camera_optical: the camera 0.3 m up, looking along base_link's x (an optical frame)
T_BASE_CAM = np.array([[0, 0, 1, 0.1], [-1, 0, 0, 0.0], [0, -1, 0, 0.3], [0, 0, 0, 1]], dtype=np.float64)


def room_depth(K: np.ndarray, h: int, w: int, forward: float) -> np.ndarray:
    """z-depth of a box room seen from its camera: floor 0.4 m below, ceiling 1.2 m above, side walls
    at +-1.5 m, the far wall 4 m ahead less ``forward``."""
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    dx, dy = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    with np.errstate(divide="ignore"):
        t = np.full((h, w), 4.0 - forward)
        t = np.minimum(t, np.where(dx != 0, 1.5 / np.abs(dx), np.inf))
        t = np.minimum(t, np.where(dy > 0, 0.4 / dy, np.inf))
        t = np.minimum(t, np.where(dy < 0, 1.2 / -dy, np.inf))
    return t.astype(np.float32)


def room_rgb(K: np.ndarray, depth: np.ndarray, forward: float) -> np.ndarray:
    """A checker texture fixed to the room (so it moves as the camera does)."""
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    x = (u - K[0, 2]) / K[0, 0] * depth
    y = (v - K[1, 2]) / K[1, 1] * depth
    z = depth + forward
    check = (np.floor(x * 4) + np.floor(y * 4) + np.floor(z * 4)) % 2
    rgb = np.stack([60 + 150 * check, 40 + 80 * (depth / 4), 200 - 120 * check], axis=-1)
    return np.clip(rgb, 0, 255).astype(np.uint8)


@dataclass
class Scene:
    K: np.ndarray
    T_cam_lidar: np.ndarray
    rgb: list
    depth: list
    ranges: list
    model: object


def room_ranges(model, forward: float) -> np.ndarray:
    """What the LiDAR sees of the whole room in its plane, beyond the camera's view too (as a real
    one does): the side walls and the far wall, along each beam (its 2-degree tilt lengthens each
    range by 1 / cos 2 deg)."""
    a = model.angle_min + model.angle_increment * np.arange(model.beams)
    with np.errstate(divide="ignore"):
        horizontal = np.minimum((4.0 - forward) / np.cos(a), np.where(np.sin(a) != 0, 1.5 / np.abs(np.sin(a)), np.inf))
    return (horizontal / np.cos(np.radians(MOUNT["tilt"]))).astype(np.float32)


def scene(n: int = 14, h: int = 48, w: int = 64, whole_room: bool = False) -> Scene:
    """``whole_room``: the LiDAR sees the room beyond the camera's view (else only what the depth
    images hold, which near the far wall is that wall alone)."""
    K = intrinsics(h, w)
    model = lidar_model(MOUNT, "test")
    rgb, depth, ranges = [], [], []
    for i in range(n):
        fwd = 0.05 * i
        d = room_depth(K, h, w, fwd)
        depth.append(d)
        rgb.append(room_rgb(K, d, fwd))
        ranges.append(room_ranges(model, fwd) if whole_room else simulate_ranges(d, K, model).ranges.astype(np.float32))
    return Scene(K, model.transform, rgb, depth, ranges, model)


def _quat(m: np.ndarray) -> tuple[float, float, float, float]:
    return tuple(float(x) for x in Rotation.from_matrix(m[:3, :3]).as_quat())   # x, y, z, w


class _Msgs:
    """Message builders for one typestore (ROS 1 field names differ: header.seq, CameraInfo's K)."""

    def __init__(self, ros1: bool) -> None:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore
        self.ros1 = ros1
        self.ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
        if ros1 and "tf2_msgs/msg/TFMessage" not in self.ts.types:
            # rosbags' Noetic store lacks tf2_msgs: its one-line definition
            self.ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                                "tf2_msgs/msg/TFMessage"))
        self.T = self.ts.types

    def serialize(self, msg, typ: str) -> bytes:
        return self.ts.serialize_ros1(msg, typ) if self.ros1 else self.ts.serialize_cdr(msg, typ)

    def header(self, stamp_ns: int, frame: str):
        t = self.T["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
        if self.ros1:
            return self.T["std_msgs/msg/Header"](seq=0, stamp=t, frame_id=frame)
        return self.T["std_msgs/msg/Header"](stamp=t, frame_id=frame)

    def image(self, stamp, frame, arr: np.ndarray, encoding: str):
        if encoding == "bgr8":
            arr = arr[..., ::-1]
        elif encoding == "16UC1":
            arr = np.round(arr * 1000).astype("<u2")
        elif encoding == "32FC1":
            arr = arr.astype("<f4")
        arr = np.ascontiguousarray(arr)
        h, w = arr.shape[:2]
        step = arr.nbytes // h
        return self.T["sensor_msgs/msg/Image"](header=self.header(stamp, frame), height=h, width=w, encoding=encoding,
                                               is_bigendian=0, step=step,
                                               data=np.frombuffer(arr.tobytes(), np.uint8))

    def compressed(self, stamp, frame, arr: np.ndarray, fmt: str = "png"):
        buf = io.BytesIO()
        Image.fromarray(arr).save(buf, format=fmt.upper())
        return self.T["sensor_msgs/msg/CompressedImage"](header=self.header(stamp, frame), format=fmt,
                                                         data=np.frombuffer(buf.getvalue(), np.uint8))

    def info(self, stamp, frame, K, h, w):
        roi = self.T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        P = np.hstack([K, np.zeros((3, 1))]).ravel()
        mats = {"D": np.zeros(5), "K": K.ravel().astype(np.float64), "R": np.eye(3).ravel(), "P": P}
        if not self.ros1:
            mats = {k.lower(): v for k, v in mats.items()}
        return self.T["sensor_msgs/msg/CameraInfo"](header=self.header(stamp, frame), height=h, width=w,
                                                    distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=roi,
                                                    **mats)

    def scan(self, stamp, frame, model, ranges):
        n = model.beams   # angle_max as the LiDAR's model says, whatever ranges holds
        return self.T["sensor_msgs/msg/LaserScan"](
            header=self.header(stamp, frame), angle_min=model.angle_min,
            angle_max=model.angle_min + (n - 1) * model.angle_increment, angle_increment=model.angle_increment,
            time_increment=0.0, scan_time=0.1, range_min=model.range_min, range_max=model.range_max,
            ranges=np.asarray(ranges, np.float32), intensities=np.zeros(0, np.float32))

    def tf(self, stamp, pairs):
        out = []
        for parent, child, m in pairs:
            x, y, z, w = _quat(m)
            tr = self.T["geometry_msgs/msg/Transform"](
                translation=self.T["geometry_msgs/msg/Vector3"](x=float(m[0, 3]), y=float(m[1, 3]), z=float(m[2, 3])),
                rotation=self.T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w))
            out.append(self.T["geometry_msgs/msg/TransformStamped"](header=self.header(stamp, parent),
                                                                    child_frame_id=child, transform=tr))
        return self.T["tf2_msgs/msg/TFMessage"](transforms=out)


def write_bag(path: Path, sc: Scene, fmt: str = "ros1", image: str = "rgb8", depth: str | None = "32FC1",
              scan_offsets=None, tf: bool = True, extra: tuple = (), cut_ranges: int = 0,
              T_cam_lidar: np.ndarray | None = None, zero_stamps: bool = False, skip_scans=(),
              skip_depth=()) -> Path:
    """Writes the scene as a bag at ``path`` (``fmt``: ros1 -> a .bag file; sqlite3 or mcap -> a ROS 2
    folder). ``scan_offsets``: seconds each scan is stamped after its image; ``extra``: more topics
    (name, 'image' | 'scan'); ``cut_ranges``: ranges dropped from each scan; ``zero_stamps``: header
    stamps left 0 (the bag's times then count); ``skip_scans`` / ``skip_depth``: frames without one."""
    m = _Msgs(fmt == "ros1")
    h, w = sc.depth[0].shape
    T = sc.T_cam_lidar if T_cam_lidar is None else T_cam_lidar
    img_type = "sensor_msgs/msg/CompressedImage" if image == "png" else "sensor_msgs/msg/Image"
    topics = {"/camera/color/image_raw": img_type, "/scan": "sensor_msgs/msg/LaserScan",
              "/camera/color/camera_info": "sensor_msgs/msg/CameraInfo"}
    if depth:
        topics["/camera/depth/image_rect"] = "sensor_msgs/msg/Image"
    if tf:
        topics["/tf_static"] = "tf2_msgs/msg/TFMessage"
    for name, kind in extra:
        topics[name] = {"image": "sensor_msgs/msg/Image", "scan": "sensor_msgs/msg/LaserScan"}[kind]
    offsets = np.zeros(len(sc.rgb)) if scan_offsets is None else np.asarray(scan_offsets, dtype=np.float64)
    records = []   # (bag time ns, topic, message)

    def at(t_ns, topic, msg):
        records.append((t_ns, topic, msg))

    t0 = T0 * 10**9
    if tf:
        at(t0 - 10**8, "/tf_static", m.tf(t0, [(BASE, CAMERA, T_BASE_CAM), (BASE, LASER, T_BASE_CAM @ T)]))
    for i in range(len(sc.rgb)):
        t = t0 + int(round(i * PERIOD * 1e9))
        ts = t + int(round(offsets[i] * 1e9))
        st, sst = (0, 0) if zero_stamps else (t, ts)
        bag_t = t + 2_000_000   # a little latency
        rgb = m.compressed(st, CAMERA, sc.rgb[i]) if image == "png" else m.image(st, CAMERA, sc.rgb[i], image)
        at(bag_t, "/camera/color/image_raw", rgb)
        at(bag_t, "/camera/color/camera_info", m.info(st, CAMERA, sc.K, h, w))
        if depth and i not in skip_depth:
            at(bag_t + 1000, "/camera/depth/image_rect", m.image(st, CAMERA, sc.depth[i], depth))
        ranges = sc.ranges[i][:len(sc.ranges[i]) - cut_ranges]
        if i not in skip_scans:
            at(ts + 1_000_000, "/scan", m.scan(sst, LASER, sc.model, ranges))
        for name, kind in extra:
            msg = m.image(st, CAMERA, sc.rgb[i], "rgb8") if kind == "image" else m.scan(sst, LASER, sc.model, ranges)
            at(bag_t + 10, name, msg)
    records.sort(key=lambda r: r[0])
    _write(path, fmt, m, topics, records)
    return path


def _write(path: Path, fmt: str, m: _Msgs, topics: dict, records: list) -> None:
    if fmt == "ros1":
        from rosbags.rosbag1 import Writer
        writer = Writer(path)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer
        plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
        writer = Writer(path, version=9, storage_plugin=plugin)
    with writer:
        conns = {t: writer.add_connection(t, typ, typestore=m.ts) for t, typ in topics.items()}
        for t_ns, topic, msg in records:
            writer.write(conns[topic], t_ns, m.serialize(msg, topics[topic]))

