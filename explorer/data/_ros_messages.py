"""Decoding the ROS messages a bag holds (images, depth images, scans, camera info, transforms) into
numpy: the message layer of :mod:`explorer.data.rosbag`, which pairs and caches them."""

from __future__ import annotations

import io
from collections import deque

import numpy as np

from explorer.errors import UserError
from explorer.scan import LaserScan

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
SCAN = "sensor_msgs/msg/LaserScan"
INFO = "sensor_msgs/msg/CameraInfo"
TF = "tf2_msgs/msg/TFMessage"
CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}
DEPTH_TYPES = {"16uc1": ("u2", 0.001), "mono16": ("u2", 0.001), "32fc1": ("f4", 1.0)}


def _stamp(msg, t_bag: int) -> int:
    """The header stamp (ns), or the bag's time where a driver left it 0."""
    st = msg.header.stamp
    ns = int(st.sec) * 1_000_000_000 + int(st.nanosec)
    return ns if ns > 0 else int(t_bag)


def _frame(msg) -> str:
    return str(msg.header.frame_id).strip().lstrip("/")


def _scan(msg, stamp: int, where: str) -> LaserScan:
    scan = LaserScan(float(msg.angle_min), float(msg.angle_increment), float(msg.range_min),
                     float(msg.range_max), np.asarray(msg.ranges, dtype=np.float32), stamp / 1e9)
    scan.check(where)
    expected = round((float(msg.angle_max) - float(msg.angle_min)) / float(msg.angle_increment)) + 1
    if abs(len(scan.ranges) - expected) > 1:
        raise UserError(f"{where}: a scan has {len(scan.ranges)} ranges, its angles (angle_min {msg.angle_min:.4g} "
                        f"to angle_max {msg.angle_max:.4g} by {msg.angle_increment:.4g}) imply {expected}")
    return scan


def _transform(tf) -> np.ndarray:
    """T_parent_child of a geometry_msgs/Transform (translation, unit quaternion)."""
    q = np.array([tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w], dtype=np.float64)
    n = np.linalg.norm(q)
    if not np.isfinite(q).all() or abs(n - 1) > 0.01:
        raise UserError(f"/tf_static: a transform's rotation is not a unit quaternion ({q.round(4).tolist()})")
    x, y, z, w = q / n
    m = np.eye(4)
    m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    m[:3, 3] = [tf.translation.x, tf.translation.y, tf.translation.z]
    return m


def _image_size(msg, msgtype: str, where: str) -> tuple[int, int]:
    if msgtype == COMPRESSED:
        return _decode_image(msg, msgtype, where).shape[:2]
    if msg.encoding.lower() not in CHANNELS:
        raise UserError(f"{where}: image encoding {msg.encoding!r}; expected one of {', '.join(CHANNELS)} "
                        "or a CompressedImage topic")
    return int(msg.height), int(msg.width)


def _decode_image(msg, msgtype: str, where: str) -> np.ndarray:
    """RGB uint8 (H, W, 3) of a raw or compressed (jpeg/png) image message."""
    if msgtype == COMPRESSED:
        from PIL import Image
        try:
            with Image.open(io.BytesIO(bytes(msg.data))) as im:
                return np.asarray(im.convert("RGB"), dtype=np.uint8)
        except (OSError, ValueError, SyntaxError) as exc:
            raise UserError(f"{where}: a compressed image does not decode ({_first_line(exc)})") from None
    enc, h, w, step = msg.encoding.lower(), int(msg.height), int(msg.width), int(msg.step)
    c = CHANNELS[enc]
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < w * c or data.size < h * step:
        raise UserError(f"{where}: an image holds {data.size} bytes, its size {w}x{h} {enc} needs {h * w * c}")
    arr = data[:h * step].reshape(h, step)[:, :w * c].reshape(h, w, c)
    if c == 1:
        return np.repeat(arr, 3, axis=2)
    return np.ascontiguousarray(arr[..., 2::-1] if enc.startswith("bgr") else arr[..., :3])


def _decode_depth(msg, where: str) -> np.ndarray:
    """Depth float32 (H, W) metres, 0 unknown, of a 16UC1 (mm) or 32FC1 (m) image message."""
    kind, scale = DEPTH_TYPES[msg.encoding.lower()]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    dtype = np.dtype((">" if msg.is_bigendian else "<") + kind)
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < w * dtype.itemsize or data.size < h * step:
        raise UserError(f"{where}: a depth image holds {data.size} bytes, its size {w}x{h} needs more")
    rows = data[:h * step].reshape(h, step)[:, :w * dtype.itemsize]
    depth = np.ascontiguousarray(rows).view(dtype).reshape(h, w).astype(np.float32) * np.float32(scale)
    depth[~np.isfinite(depth) | (depth < 0)] = 0.0
    return depth


# -- pairing and calibration ----------------------------------------------------------------------


def _nearest(times: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each of ``t`` the index of the nearest of the sorted ``times`` and its offset (ns)."""
    j = np.clip(np.searchsorted(times, t), 1, max(len(times) - 1, 1))
    lo = np.clip(j - 1, 0, len(times) - 1)
    hi = np.clip(j, 0, len(times) - 1)
    pick = np.where(np.abs(times[lo] - t) <= np.abs(times[hi] - t), lo, hi)
    return pick, np.abs(times[pick] - t)


def _intrinsics(info, where: str) -> np.ndarray:
    """K from CameraInfo (``k`` in ROS 2, ``K`` in ROS 1 as rosbags gives it)."""
    k = getattr(info, "k", None)
    k = getattr(info, "K", None) if k is None else k
    K = np.asarray(k, dtype=np.float64).reshape(-1)
    if K.size != 9 or not np.isfinite(K).all() or K[0] <= 0 or K[4] <= 0:
        raise UserError(f"{where}: the CameraInfo's K ({K.round(3).tolist()}) is not a camera matrix "
                        "(fx, fy > 0); is the camera calibrated?")
    return K.reshape(3, 3)


def _tf_chain(edges: dict, source: str, target: str) -> np.ndarray | None:
    """T_target_source through the static transform tree (breadth first), or None without a path."""
    if source == target:
        return np.eye(4)
    seen, queue = {source: np.eye(4)}, deque([source])
    while queue:
        node = queue.popleft()
        for other, T_other_node in edges.get(node, []):
            if other not in seen:
                seen[other] = T_other_node @ seen[node]
                if other == target:
                    return seen[other]
                queue.append(other)
    return None


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return (text[0] if text else type(exc).__name__)[:160]
