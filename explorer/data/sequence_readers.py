"""Readers of real image sequences: a KITTI raw drive and a plain folder of consecutive frames.

Both check their layout when opened (missing folders, files, neighbours, intrinsics, frames of
different sizes), so a malformed sequence is one clear error before any training starts. The last
tenth of the targets (at least one) is the validation split, the rest the training split.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from explorer.data.odometry import camera_motion
from explorer.data.readers import (calib_matrix, check_projection, check_rotation, open_image, read_depth_png,
                                   read_image, read_velodyne, ring_mask, sparse_depth)
from explorer.scan import (LidarModel, check_principal_point, project_scan, read_intrinsics,  # noqa: F401
                           read_lidar_yaml, read_ranges)
from explorer.data.sequences import SequenceSample
from explorer.data.splits import VAL_SHARE, split_range
from explorer.errors import UserError
from explorer.files import read_text

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def _split_targets(count: int, split: str, where: Path, share: float = VAL_SHARE) -> range:
    """Targets are frames 1..count-2 (each needs both neighbours); val is the last ``share`` of them,
    two targets left out before it so that no frame of a validation sample is in a training one."""
    return split_range(max(count - 2, 0), split, str(where), share, gap=2, start=1,
                       what="target frame(s) (frames with both neighbours)")


def _sample_names(names: list[str], targets: range) -> list[str]:
    """Every frame the samples of ``targets`` read: each target and its two neighbours."""
    return sorted({names[t + d] for t in targets for d in (-1, 0, 1)})


def _check_consecutive(paths: list[Path], where: Path) -> None:
    """Frames named by numbers must follow each other: a gap means a target lost a neighbour."""
    numbers = []
    for p in paths:
        m = re.search(r"(\d+)$", p.stem)
        if m is None:
            return  # names without numbers: the sorted order is the sequence
        numbers.append(int(m.group(1)))
    for a, b, p in zip(numbers, numbers[1:], paths[1:]):
        if b != a + 1:
            raise UserError(f"{where}: frame {a + 1} is missing before {p.name} (the sequence must be "
                            "consecutive: every target needs its neighbours t-1 and t+1)")


def _check_sizes(paths: list[Path]) -> tuple[int, int]:
    sizes = {}
    for p in paths:
        with open_image(p) as im:
            sizes.setdefault(im.size, p)
    if len(sizes) > 1:
        (a, pa), (b, pb) = list(sizes.items())[:2]
        raise UserError(f"frames differ in size: {pa.name} is {a[0]}x{a[1]}, {pb.name} is {b[0]}x{b[1]} "
                        "(a sequence must have one image size)")
    w, h = next(iter(sizes))
    return h, w


def _rgb(path: Path) -> np.ndarray:
    return read_image(path, "RGB")


def read_poses(path: Path, frames: int) -> list[np.ndarray]:
    """One camera-to-world pose per frame: 12 numbers a line (a 3x4 matrix, KITTI odometry's format),
    each finite with an invertible rotation part."""
    rows = [line.split() for line in read_text(path, "poses file").splitlines() if line.strip()]
    if len(rows) != frames or any(len(r) != 12 for r in rows):
        raise UserError(f"{path}: needs one line of 12 numbers per frame ({frames} frames)")
    poses = []
    for line, r in enumerate(rows, 1):
        try:
            m = np.eye(4)
            m[:3, :4] = np.array([float(x) for x in r]).reshape(3, 4)
        except ValueError:
            raise UserError(f"{path}: line {line}: poses must be numbers (12 per line)") from None
        if not np.isfinite(m).all():
            raise UserError(f"{path}: line {line}: a pose must be finite numbers (found nan or inf)")
        if abs(np.linalg.det(m[:3, :3])) < 1e-6:
            raise UserError(f"{path}: line {line}: the rotation part is singular (not a camera pose)")
        poses.append(m)
    return poses


# -- a plain folder -------------------------------------------------------------------------------
class FrameFolder:
    """``FOLDER/*.png|jpg`` consecutive frames (sorted by name) and ``FOLDER/intrinsics.txt``.
    Optional: ``FOLDER/depth/<name>.png`` 16-bit millimetres (evaluation, and the simulated scan),
    ``FOLDER/poses.txt`` (one line per frame: the 12 numbers of a 3x4 camera-to-world matrix, KITTI
    odometry's format), and a real LiDAR's scans: ``FOLDER/scans/<name>.csv|.npy`` (one range per
    beam, metres; inf, nan or 0 = no return) with ``FOLDER/lidar.yaml`` (the LiDAR and its mount,
    :func:`explorer.scan.read_lidar_yaml`; or the data spec's LiDAR options). Without poses.txt, the
    validation samples take the camera's motion from the scans (:mod:`explorer.data.odometry`)."""

    kind = "frames"
    max_depth = 10.0

    def __init__(self, root: Path, split: str, share: float = VAL_SHARE, lidar: LidarModel | None = None) -> None:
        self.root = root
        if not root.is_dir():
            raise UserError(f"{root}: not a folder (frames:FOLDER needs a folder of consecutive images and "
                            "intrinsics.txt)")
        self.paths = sorted(p for p in root.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if len(self.paths) < 3:
            raise UserError(f"{root}: {len(self.paths)} frame(s); a sequence needs at least 3 consecutive images")
        if not (root / "intrinsics.txt").is_file():
            raise UserError(f"{root}: missing intrinsics.txt (write fx fy cx cy, or the 3x3 matrix K)")
        self.K = read_intrinsics(root / "intrinsics.txt")
        _check_consecutive(self.paths, root)
        self.shape = _check_sizes(self.paths)
        check_principal_point(self.K, self.shape, str(root / "intrinsics.txt"))
        self.poses = self._read_poses(root / "poses.txt")
        self.targets = _split_targets(len(self.paths), split, root, share)
        self.lidar = self._scan_model(lidar)
        if self.lidar is not None:
            self.max_depth = self.lidar.range_max
        # validation without poses.txt: the camera's motion as the scans measure it (explorer.data.odometry)
        self.scan_poses = ({t: self._scan_poses(t) for t in self.targets}
                           if split == "val" and self.poses is None and self.lidar is not None else {})

    def _scan_poses(self, t: int) -> list[np.ndarray] | None:
        """Camera-to-world of frames t-1, t, t+1 with frame t's camera as the world, from scan matching;
        None where a neighbour has no scan or the scans do not pin the motion down."""
        files = [self._scan_file(self.paths[k].stem) for k in (t - 1, t, t + 1)]
        if any(f is None for f in files):
            return None
        scans = [self.lidar.scan(read_ranges(f, self.lidar.beams)) for f in files]
        motions = [camera_motion(scans[k], scans[1], self.lidar.transform) for k in (0, 2)]
        return None if any(m is None for m in motions) else [motions[0], np.eye(4), motions[1]]

    def _scan_model(self, given: LidarModel | None) -> LidarModel | None:
        """The LiDAR of ``scans/`` (lidar.yaml, else the spec's options), None without scans/."""
        scans, yaml_file = self.root / "scans", self.root / "lidar.yaml"
        if not scans.is_dir():
            return None
        if yaml_file.is_file() and given is not None:
            raise UserError(f"{self.root}: lidar.yaml and the data spec's LiDAR options both describe the LiDAR; "
                            "keep one")
        if not yaml_file.is_file() and given is None:
            raise UserError(f"{self.root}: scans/ needs the LiDAR that made them: write lidar.yaml (fov, resolution, "
                            "range_min, range_max and the mount: height, tilt, ... or T_cam_lidar)")
        model = read_lidar_yaml(yaml_file) if yaml_file.is_file() else given
        missing = [p.stem for p in self.paths[1:-1] if not self._scan_file(p.stem)]
        if missing:
            raise UserError(f"{scans}: no scan for frame {missing[0]} (scans/{missing[0]}.csv or .npy; every frame "
                            "that is a target needs one)")
        return model

    def _scan_file(self, stem: str) -> Path | None:
        return next((f for f in (self.root / "scans" / f"{stem}.csv", self.root / "scans" / f"{stem}.npy")
                     if f.is_file()), None)

    def frame_names(self) -> list[str]:
        return _sample_names([p.name for p in self.paths], self.targets)

    def _read_poses(self, path: Path) -> list[np.ndarray] | None:
        return read_poses(path, len(self.paths)) if path.is_file() else None

    def __len__(self) -> int:
        return len(self.targets)

    def __getitem__(self, i: int) -> SequenceSample:
        t = self.targets[i]
        frames = [_rgb(self.paths[t + d]) for d in (-1, 0, 1)]
        depth_path = self.root / "depth" / f"{self.paths[t].stem}.png"
        depth = np.zeros(self.shape, np.float32)
        if depth_path.is_file():
            depth = read_depth_png(depth_path)
            if depth.shape != self.shape:
                raise UserError(f"{depth_path}: {depth.shape} differs from the frames' {self.shape}")
        poses = [self.poses[t + d] for d in (-1, 0, 1)] if self.poses else self.scan_poses.get(t)
        points = None
        if self.lidar is not None:
            f = self._scan_file(self.paths[t].stem)
            scan = self.lidar.scan(read_ranges(f, self.lidar.beams))
            points = project_scan(scan, self.lidar.transform, self.K, self.shape)
            if len(points.z) == 0:
                raise UserError(f"{f}: no return of this scan lands in the image: check the mount in lidar.yaml "
                                "(height, tilt, ... or T_cam_lidar) and the field of view")
        return SequenceSample(frames, depth, self.K, poses, None, self.paths[t].stem, points)


# -- a KITTI raw drive ----------------------------------------------------------------------------
def _read_kv(path: Path) -> dict[str, np.ndarray]:
    out = {}
    for line in read_text(path, 'calibration file').splitlines():
        k, sep, v = line.partition(":")
        if not sep:
            continue
        try:
            out[k.strip()] = np.array([float(x) for x in v.split()])
        except ValueError:
            continue  # e.g. calib_time: a date
    return out


def _rigid(values: dict[str, np.ndarray], path: Path) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = calib_matrix(values, "R", (3, 3), path), calib_matrix(values, "T", (3,), path)
    check_rotation(m[:3, :3], path, "R")
    return m


def oxts_pose(packet: np.ndarray, scale: float) -> np.ndarray:
    """IMU-to-world 4x4 from one OXTS packet (lat, lon, alt, roll, pitch, yaw, ...): Mercator
    coordinates in metres, as KITTI's devkit computes them."""
    lat, lon, alt, roll, pitch, yaw = packet[:6]
    r_earth = 6378137.0
    tx = scale * lon * np.pi * r_earth / 180.0
    ty = scale * r_earth * np.log(np.tan((90.0 + lat) * np.pi / 360.0))
    cx, sx, cy, sy, cz, sz = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rz @ ry @ rx, (tx, ty, alt)
    return m


class KittiDrive:
    """A KITTI raw drive: ``DRIVE/image_02/data/*.png``, ``DRIVE/velodyne_points/data/*.bin``,
    optional ``DRIVE/oxts/data/*.txt``; ``calib_cam_to_cam.txt`` and ``calib_velo_to_cam.txt`` (and
    ``calib_imu_to_velo.txt`` for poses) in DRIVE or its parent (the date folder). Ground truth is
    the projected point cloud; the 2D LiDAR is the laser ring nearest ``elevation_deg``."""

    kind = "kitti"
    max_depth = 80.0

    def __init__(self, root: Path, split: str, elevation_deg: float = 0.0, share: float = VAL_SHARE) -> None:
        self.root, self.elevation = root, elevation_deg
        images = root / "image_02" / "data"
        if not images.is_dir():
            raise UserError(f"{root}: missing image_02/data/ (expected a KITTI raw drive folder)")
        self.paths = sorted(p for p in images.iterdir() if p.suffix.lower() == ".png")
        if len(self.paths) < 3:
            raise UserError(f"{images}: {len(self.paths)} frame(s); a sequence needs at least 3")
        _check_consecutive(self.paths, images)
        velo = root / "velodyne_points" / "data"
        missing = [p.stem for p in self.paths if not (velo / f"{p.stem}.bin").is_file()]
        if missing:
            raise UserError(f"{velo}: no point cloud for frame {missing[0]} (every frame needs its .bin)")
        self.shape = _check_sizes(self.paths)
        cam_file, velo_file = self._calib("calib_cam_to_cam.txt"), self._calib("calib_velo_to_cam.txt")
        cam = _read_kv(cam_file)
        p2 = calib_matrix(cam, "P_rect_02", (3, 4), cam_file)
        check_projection(p2, cam_file, "P_rect_02")
        self.K = p2[:, :3].copy()
        # rectified camera 2 from the velodyne: R_rect_00, then camera 2's offset along x
        rect = np.eye(4)
        rect[:3, :3] = calib_matrix(cam, "R_rect_00", (3, 3), cam_file)
        check_rotation(rect[:3, :3], cam_file, "R_rect_00")
        offset = np.eye(4)
        offset[0, 3] = p2[0, 3] / p2[0, 0]
        self.cam_from_velo = offset @ rect @ _rigid(_read_kv(velo_file), velo_file)
        self.poses = self._oxts_poses()
        self.targets = _split_targets(len(self.paths), split, root, share)

    def frame_names(self) -> list[str]:
        return _sample_names([p.name for p in self.paths], self.targets)

    def _calib(self, name: str) -> Path:
        for folder in (self.root, self.root.parent):
            if (folder / name).is_file():
                return folder / name
        raise UserError(f"{self.root}: missing {name} (in the drive folder or its parent)")

    def _oxts_poses(self) -> list[np.ndarray] | None:
        oxts = self.root / "oxts" / "data"
        imu_file = next((f / "calib_imu_to_velo.txt" for f in (self.root, self.root.parent)
                         if (f / "calib_imu_to_velo.txt").is_file()), None)
        if not oxts.is_dir() or imu_file is None:
            return None
        files = [oxts / f"{p.stem}.txt" for p in self.paths]
        if not all(f.is_file() for f in files):
            return None
        packets = []
        for f in files:
            try:
                packets.append(np.array([float(x) for x in f.read_text().split()]))
            except ValueError:
                raise UserError(f"{f}: malformed OXTS packet (expected numbers)") from None
        if any(len(p) < 6 for p in packets):
            raise UserError(f"{oxts}: an OXTS packet has fewer than 6 values (lat lon alt roll pitch yaw)")
        scale = np.cos(packets[0][0] * np.pi / 180.0)
        cam_from_imu = self.cam_from_velo @ _rigid(_read_kv(imu_file), imu_file)
        imu_from_cam = np.linalg.inv(cam_from_imu)
        return [oxts_pose(p, scale) @ imu_from_cam for p in packets]

    def __len__(self) -> int:
        return len(self.targets)

    def _project(self, points: np.ndarray) -> np.ndarray:
        cam = self.cam_from_velo @ np.c_[points[:, :3], np.ones(len(points))].T
        front = cam[2] > 0.5
        img = self.K @ cam[:3, front]
        u, v, z = img[0] / img[2], img[1] / img[2], cam[2, front]
        h, w = self.shape
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        return sparse_depth(np.round(u[inside]).astype(int).clip(0, w - 1),
                            np.round(v[inside]).astype(int).clip(0, h - 1), z[inside], self.shape)

    def __getitem__(self, i: int) -> SequenceSample:
        t = self.targets[i]
        frames = [_rgb(self.paths[t + d]) for d in (-1, 0, 1)]
        velo = self.root / "velodyne_points" / "data" / f"{self.paths[t].stem}.bin"
        points = read_velodyne(velo)
        depth = self._project(points)
        scan_image = self._project(points[ring_mask(points, self.elevation)])
        poses = [self.poses[t + d] for d in (-1, 0, 1)] if self.poses else None
        return SequenceSample(frames, depth, self.K, poses, scan_image, self.paths[t].stem)
