"""A real 2D LiDAR's scan in the image: ranges by angle, the mount, the camera, and back.

A scan is what a ROS ``sensor_msgs/LaserScan`` holds: ``ranges`` at angles ``angle_min + i *
angle_increment`` in the LiDAR's plane, valid within ``[range_min, range_max]``. The LiDAR frame
follows ROS (REP 103: x forward, y left, z up); the camera frame is the optical one (x right, y
down, z forward). Return ``i`` is the point ``(r cos a, r sin a, 0)`` of the LiDAR frame,
``T_cam_lidar`` (4x4, rigid) takes it to the camera, and ``K`` to the pixel ``(u, v)`` with depth
``z`` (pixel-index coordinates: pixel j's centre at j). Returns out of range, behind the camera or
outside the image are dropped.

:class:`LidarModel` is a sensor and its mount. It projects real scans (:func:`project_scan`), and it
simulates them where the data has none (:func:`simulate_scan_points`): rays at its resolution cast
into the depth map, with its noise and dropouts, then projected the same way.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from explorer.errors import UserError
from explorer.files import parse_yaml, read_text

#: the rotation from the LiDAR frame (x forward, y left, z up) to the optical frame (x right, y down,
#: z forward) of a camera looking the same way
LIDAR_TO_OPTICAL = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


@dataclass(frozen=True)
class LaserScan:
    """One sweep: ``ranges`` (metres; inf, nan or out of range = no return) by angle (radians)."""

    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float
    ranges: np.ndarray = field(repr=False)
    stamp: float = 0.0   # seconds

    @property
    def angles(self) -> np.ndarray:
        return self.angle_min + self.angle_increment * np.arange(len(self.ranges))

    def check(self, where: str) -> None:
        params = (self.angle_min, self.angle_increment, self.range_min, self.range_max)
        if not all(math.isfinite(float(p)) for p in params):
            raise UserError(f"{where}: the scan's angles and range limits must be finite numbers")
        if self.angle_increment == 0:
            raise UserError(f"{where}: angle_increment is 0 (the scan's beams would all point one way)")
        if not 0 <= self.range_min < self.range_max:
            raise UserError(f"{where}: range_min {self.range_min:g} and range_max {self.range_max:g} must satisfy "
                            "0 <= range_min < range_max")
        if np.asarray(self.ranges).ndim != 1 or len(self.ranges) == 0:
            raise UserError(f"{where}: ranges must be one non-empty list of numbers")


@dataclass(frozen=True)
class ScanPoints:
    """A scan's returns in an image: column ``u``, row ``v`` (float pixels) and depth ``z`` (metres)."""

    u: np.ndarray
    v: np.ndarray
    z: np.ndarray

    def transformed(self, box: tuple[int, int, int, int], size: tuple[int, int], flip: bool = False) -> "ScanPoints":
        """The points after cropping ``box`` (top, left, height, width) and resizing it to ``size``, then
        mirroring left-right if ``flip``: as :func:`scale_intrinsics` moves K."""
        top, left, h, w = box
        sy, sx = size[0] / h, size[1] / w
        u = (self.u - left + 0.5) * sx - 0.5
        v = (self.v - top + 0.5) * sy - 0.5
        if flip:
            u = size[1] - 1 - u
        return ScanPoints(u, v, self.z)


def _holds_bool(value) -> bool:
    """Whether ``value`` (a number, or nested lists / arrays of them) holds a boolean anywhere: YAML's
    true / false would pass as 1 / 0 (bool is an int in Python), a typo taken for a number."""
    if isinstance(value, (bool, np.bool_)):
        return True
    if isinstance(value, np.ndarray):
        return value.dtype.kind == "b" or (value.dtype == object and any(_holds_bool(v) for v in value.ravel()))
    if isinstance(value, (list, tuple)):
        return any(_holds_bool(v) for v in value)
    return False


def rigid_transform(matrix, where: str) -> np.ndarray:
    """``matrix`` as a 4x4 rigid transform (rotation with determinant +1, last row 0 0 0 1), or a
    :class:`UserError` saying what is wrong with it."""
    if _holds_bool(matrix):
        raise UserError(f"{where}: T_cam_lidar holds true/false; write its entries as numbers (1, 0)")
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise UserError(f"{where}: T_cam_lidar must be a 4x4 matrix of numbers") from None
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4):
        raise UserError(f"{where}: T_cam_lidar must be a 4x4 matrix (or its top 3x4), got shape {m.shape}")
    if not np.isfinite(m).all():
        raise UserError(f"{where}: T_cam_lidar has NaN or infinite entries")
    r = m[:3, :3]
    if not np.allclose(m[3], [0, 0, 0, 1]) or not np.allclose(r @ r.T, np.eye(3), atol=1e-4) \
            or np.linalg.det(r) < 0:
        raise UserError(f"{where}: T_cam_lidar is not a rigid transform (its rotation part must be orthonormal "
                        "with determinant +1, its last row 0 0 0 1)")
    return m


def mount_transform(height: float = 0.0, forward: float = 0.0, lateral: float = 0.0, tilt_deg: float = 0.0,
                    roll_deg: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    """``T_cam_lidar`` of a LiDAR ``height`` metres above the camera's optical centre, ``forward`` ahead
    of it and ``lateral`` to its right, its plane pitched down by ``tilt_deg``, rolled clockwise (as
    the camera sees it) by ``roll_deg`` and turned right by ``yaw_deg``. All zero: the paper's level
    mount at the optical centre, whose scan falls on the image's centre row."""
    t, r, y = np.radians([tilt_deg, roll_deg, yaw_deg])
    # in the camera's frame: pitch about x (down is +y), roll about z, yaw about y
    pitch = np.array([[1, 0, 0], [0, np.cos(t), np.sin(t)], [0, -np.sin(t), np.cos(t)]])
    roll = np.array([[np.cos(r), -np.sin(r), 0], [np.sin(r), np.cos(r), 0], [0, 0, 1]])
    yaw = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])
    m = np.eye(4)
    m[:3, :3] = yaw @ roll @ pitch @ LIDAR_TO_OPTICAL
    m[:3, 3] = (lateral, -height, forward)
    return m


def project_scan(scan: LaserScan, T_cam_lidar: np.ndarray, K: np.ndarray, shape: tuple[int, int]) -> ScanPoints:
    """The returns of ``scan`` that land in an image of ``shape`` (H, W) seen through ``K``."""
    r = np.asarray(scan.ranges, dtype=np.float64)
    a = scan.angles
    valid = np.isfinite(r) & (r >= scan.range_min) & (r <= scan.range_max) & (r > 0)
    r, a = r[valid], a[valid]
    lidar = np.stack([r * np.cos(a), r * np.sin(a), np.zeros_like(r)])
    cam = T_cam_lidar[:3, :3] @ lidar + T_cam_lidar[:3, 3:4]
    front = cam[2] > 1e-3
    cam = cam[:, front]
    pix = K @ cam
    u, v, z = pix[0] / pix[2], pix[1] / pix[2], cam[2]
    h, w = shape
    inside = (u > -0.5) & (u < w - 0.5) & (v > -0.5) & (v < h - 0.5)
    return ScanPoints(u[inside], v[inside], z[inside])


def column_scan(points: ScanPoints, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, int]:
    """Per image column the nearest return: (scan (W,) metres, 0 = none; rows (W,), the row of each
    column's return, interpolated between columns that have one; the median row of the returns)."""
    h, w = shape
    scan = np.zeros(w, np.float32)
    rows = np.full(w, h // 2, np.int64)
    if len(points.z) == 0:
        return scan, rows, h // 2
    cols = np.clip(np.round(points.u).astype(np.int64), 0, w - 1)
    prow = np.clip(np.round(points.v).astype(np.int64), 0, h - 1)
    order = np.argsort(-points.z)   # the nearest return of a column is written last and wins
    scan[cols[order]] = points.z[order]
    rows[cols[order]] = prow[order]
    have = scan > 0
    row = int(np.median(rows[have]))
    rows = np.round(np.interp(np.arange(w), np.nonzero(have)[0], rows[have])).astype(np.int64)
    return scan, rows, row


@dataclass(frozen=True)
class LidarModel:
    """A 2D LiDAR and its mount: the beams (``angle_min`` to ``angle_max`` by ``angle_increment``, radians), the range
    limits, ``T_cam_lidar`` (a tuple of 16 numbers, row-major) and, for simulated scans, range
    ``noise`` (standard deviation, metres) and ``dropout`` (the probability a return is lost)."""

    angle_min: float = -math.pi / 2
    angle_max: float = math.pi / 2
    angle_increment: float = math.radians(0.25)
    range_min: float = 0.05
    range_max: float = 10.0
    T_cam_lidar: tuple[float, ...] = tuple(mount_transform().ravel())
    noise: float = 0.0
    dropout: float = 0.0

    @property
    def transform(self) -> np.ndarray:
        return np.asarray(self.T_cam_lidar, dtype=np.float64).reshape(4, 4)

    @property
    def beams(self) -> int:
        return max(int(math.floor((self.angle_max - self.angle_min) / self.angle_increment + 1e-6)) + 1, 1)

    def scan(self, ranges: np.ndarray, stamp: float = 0.0) -> LaserScan:
        return LaserScan(self.angle_min, self.angle_increment, self.range_min, self.range_max,
                         np.asarray(ranges, dtype=np.float32), stamp)


def _pixel_depth(depth: np.ndarray, K: np.ndarray, cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The depth map's value under each camera point (nearest pixel; 0 outside), and whether inside."""
    h, w = depth.shape
    pix = K @ cam
    z = np.where(pix[2] > 1e-6, pix[2], np.nan)
    u, v = np.round(pix[0] / z), np.round(pix[1] / z)
    inside = (cam[2] > 1e-3) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    ui, vi = np.where(inside, u, 0).astype(np.int64), np.where(inside, v, 0).astype(np.int64)
    return np.where(inside, depth[vi, ui], 0.0), inside


#: ray samples per beam (geometric spacing from range_min to range_max), refined between the last two
RAY_SAMPLES = 192


def simulate_ranges(depth: np.ndarray, K: np.ndarray, model: LidarModel,
                    rng: np.random.Generator | None = None) -> LaserScan:
    """The scan ``model`` would report in the scene of ``depth`` (H, W metres, 0 = unknown): each beam
    marched out from the LiDAR until it passes behind the depth map's surface; beams that leave the
    image or meet no known surface return nothing (inf). Then noise and dropouts, if the model has them."""
    angles = model.angle_min + model.angle_increment * np.arange(model.beams)
    T = model.transform
    t = np.geomspace(max(model.range_min, 0.02), model.range_max, RAY_SAMPLES)
    dirs = T[:3, :3] @ np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)])   # (3, B)
    pts = T[:3, 3:4, None] + dirs[:, :, None] * t[None, None, :]                          # (3, B, S)
    surface, inside = _pixel_depth(depth, K, pts.reshape(3, -1))
    surface, inside = surface.reshape(pts.shape[1:]), inside.reshape(pts.shape[1:])
    behind = inside & (surface > 0) & (pts[2] >= surface)
    hit = behind.any(axis=1)
    first = behind.argmax(axis=1)
    ranges = np.full(len(angles), np.inf)
    b = np.nonzero(hit)[0]
    k = first[b]
    # the crossing between the sample before and the first one behind the surface, linearly
    prev = np.maximum(k - 1, 0)
    gap_prev = surface[b, prev] - pts[2, b, prev]
    gap_hit = pts[2, b, k] - surface[b, k]
    frac = np.where((k > 0) & (gap_prev > 0), gap_prev / np.maximum(gap_prev + gap_hit, 1e-9), 1.0)
    ranges[b] = t[prev] + frac * (t[k] - t[prev])
    if rng is not None and model.noise > 0:
        ranges = ranges + rng.normal(0.0, model.noise, len(ranges))
    if rng is not None and model.dropout > 0:
        ranges[rng.random(len(ranges)) < model.dropout] = np.inf
    ranges[(ranges < model.range_min) | (ranges > model.range_max)] = np.inf
    return model.scan(ranges)


def simulate_scan_points(depth: np.ndarray, K: np.ndarray, model: LidarModel,
                         rng: np.random.Generator | None = None) -> ScanPoints:
    """:func:`simulate_ranges`, projected into the image of ``depth`` as a real scan is."""
    return project_scan(simulate_ranges(depth, K, model, rng), model.transform, K, depth.shape)


def check_camera_matrix(K, where: str) -> np.ndarray:
    """``K`` as a 3x3 float64 camera matrix (finite, positive focal lengths, last row 0 0 1), or one
    UserError line."""
    try:
        m = np.asarray(K, dtype=np.float64)
    except (TypeError, ValueError):
        raise UserError(f"{where}: the camera matrix K must be numbers") from None
    if m.shape != (3, 3):
        raise UserError(f"{where}: the camera matrix K must be 3x3, got shape {m.shape}")
    if not np.isfinite(m).all():
        raise UserError(f"{where}: intrinsics must be finite numbers (found nan or inf)")
    if m[0, 0] <= 0 or m[1, 1] <= 0:
        raise UserError(f"{where}: focal lengths fx={m[0, 0]:g}, fy={m[1, 1]:g} must be positive (in pixels)")
    if not np.allclose(m[2], [0, 0, 1]) or m[1, 0] != 0:
        raise UserError(f"{where}: not a camera matrix: its last row must be 0 0 1 and K[1][0] zero")
    return m


def check_principal_point(K, shape: tuple[int, ...], where: str) -> None:
    """Refuses ``K`` whose principal point (cx, cy) lies outside an image of ``shape`` (H, W, ...): such
    intrinsics belong to another resolution or have fx, fy and cx, cy swapped, and every projected
    return would land off the image. The image's edges are -0.5 and W - 0.5 in pixel-index coordinates,
    0 and W where a pixel's corner is 0 (as some calibration tools write it): either is accepted."""
    h, w = int(shape[0]), int(shape[1])
    cx, cy = float(np.asarray(K)[0, 2]), float(np.asarray(K)[1, 2])
    if not (-0.5 <= cx <= w and -0.5 <= cy <= h):
        raise UserError(f"{where}: the principal point cx={cx:g}, cy={cy:g} lies outside the {w}x{h} image; give "
                        f"the intrinsics of these frames in their pixels (cx near {w / 2:g}, cy near {h / 2:g}), "
                        "in the order fx fy cx cy")


def read_intrinsics(path: str | Path) -> np.ndarray:
    """K from ``fx fy cx cy`` (4 numbers) or its 9 entries, in pixels of the image it belongs to,
    checked to be a camera matrix before any tensor sees it."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such intrinsics file (write fx fy cx cy, or the 3x3 matrix K)")
    try:
        values = [float(x) for x in read_text(path, "intrinsics file").replace(",", " ").split()]
    except ValueError:
        raise UserError(f"{path}: intrinsics must be numbers (fx fy cx cy, or the 9 entries of K)") from None
    if len(values) == 4:
        fx, fy, cx, cy = values
        values = [fx, 0, cx, 0, fy, cy, 0, 0, 1]
    elif len(values) != 9:
        raise UserError(f"{path}: {len(values)} numbers; give fx fy cx cy, or the 9 entries of K")
    return check_camera_matrix(np.array(values, dtype=np.float64).reshape(3, 3), str(path))


def scale_intrinsics(K: np.ndarray, box: tuple[float, float, float, float], size: tuple[int, int]) -> np.ndarray:
    """Intrinsics after cropping ``box`` (top, left, h, w) and resizing it to ``size``, in
    pixel-index coordinates (a pixel's centre at its index)."""
    top, left, h, w = box
    sy, sx = size[0] / h, size[1] / w
    out = np.array(K, dtype=np.float64).copy()
    out[0, 0], out[1, 1] = K[0, 0] * sx, K[1, 1] * sy
    out[0, 2] = (K[0, 2] - left + 0.5) * sx - 0.5
    out[1, 2] = (K[1, 2] - top + 0.5) * sy - 0.5
    return out


def read_ranges(path: Path, beams: int | None = None) -> np.ndarray:
    """A scan's ranges from ``.csv`` (one row, or one value a line) or ``.npy``; ``beams``: the count
    the LiDAR's model gives, checked."""
    try:
        if path.suffix.lower() == ".npy":
            ranges = np.load(path, allow_pickle=False).astype(np.float64).ravel()
        else:
            text = read_text(path, "scan file").replace(",", " ").split()
            ranges = np.array([float(x) for x in text], dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: not a list of ranges ({str(exc).splitlines()[0][:80]})") from None
    if ranges.size == 0:
        raise UserError(f"{path}: no ranges")
    if beams is not None and ranges.size != beams:
        raise UserError(f"{path}: {ranges.size} ranges, the LiDAR's model has {beams} beams "
                        "(angle_min .. angle_max by angle_increment); give one range per beam")
    return ranges


#: the keys of a LiDAR model (a ``lidar.yaml``, or a data spec's options) and what each is
LIDAR_KEYS = {
    "fov": "field of view, degrees, centred on the LiDAR's x axis (or angle_min / angle_max, radians)",
    "resolution": "angular resolution, degrees (or angle_increment, radians)",
    "range_min": "metres", "range_max": "metres",
    "noise": "range noise, standard deviation in metres (simulated scans)",
    "dropout": "probability that a return is lost (simulated scans)",
    "height": "metres the LiDAR sits above the camera's optical centre",
    "forward": "metres ahead of the optical centre", "lateral": "metres to its right",
    "tilt": "degrees the scan plane is pitched down", "roll": "degrees rolled clockwise", "yaw": "degrees turned right",
}
RADIAN_KEYS = ("angle_min", "angle_max", "angle_increment")
MOUNT_KEYS = ("height", "forward", "lateral", "tilt", "roll", "yaw")


#: the widest span of beams a 2D LiDAR sweeps: a full turn (degrees for fov, radians for angle_min ..
#: angle_max, with a little slack for a LaserScan's float32 angles rounded when written out)
MAX_FOV_DEG = 360.0
MAX_SPAN_RAD = 2 * math.pi + 1e-3


def _number(value, key: str, where: str) -> float:
    if _holds_bool(value):   # bool is an int: `fov: true` would be read as fov 1
        raise UserError(f"{where}: {key} must be a number, got {str(value).lower()} (a YAML true/false); "
                        "write the number")
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise UserError(f"{where}: {key} must be a number, got {value!r}") from None
    if not math.isfinite(x):
        raise UserError(f"{where}: {key} must be finite, got {value!r}")
    return x


def lidar_model(options: dict, where: str, base: LidarModel = LidarModel()) -> LidarModel:
    """A :class:`LidarModel` from ``options`` (the keys of :data:`LIDAR_KEYS`, radian angles, or a
    ``T_cam_lidar`` matrix in place of the mount keys), each checked, on top of ``base``."""
    unknown = sorted(set(options) - set(LIDAR_KEYS) - set(RADIAN_KEYS) - {"T_cam_lidar", "mount"})
    if unknown:
        raise UserError(f"{where}: unknown LiDAR key {unknown[0]!r}; use {', '.join(LIDAR_KEYS)}, "
                        f"{', '.join(RADIAN_KEYS)} or T_cam_lidar")
    opts = flat_lidar_options(options, where)
    values = {k: _number(v, k, where) for k, v in opts.items() if k != "T_cam_lidar"}
    angle_min, angle_max, step = _beams(values, where, base)
    if "T_cam_lidar" in opts and any(k in values for k in MOUNT_KEYS):
        raise UserError(f"{where}: give the mount either as T_cam_lidar or as height/tilt/..., not both")
    if "T_cam_lidar" in opts:
        matrix = opts["T_cam_lidar"]
        if isinstance(matrix, str):   # a data spec's option: the 12 (or 16) numbers joined by ':' (or ',', spaces)
            numbers = [_number(x, "T_cam_lidar", where) for x in re.split(r"[:,\s]+", matrix.strip()) if x]
            if len(numbers) not in (12, 16):
                raise UserError(f"{where}: T_cam_lidar takes 12 numbers (its top 3x4) joined by ':'")
            matrix = np.array(numbers).reshape(-1, 4)
        transform = rigid_transform(matrix, where)
    elif any(k in values for k in MOUNT_KEYS):
        transform = mount_transform(values.get("height", 0.0), values.get("forward", 0.0), values.get("lateral", 0.0),
                                    values.get("tilt", 0.0), values.get("roll", 0.0), values.get("yaw", 0.0))
    else:
        transform = base.transform
    model = LidarModel(angle_min, angle_max, step, values.get("range_min", base.range_min),
                       values.get("range_max", base.range_max), tuple(float(x) for x in transform.ravel()),
                       values.get("noise", base.noise), values.get("dropout", base.dropout))
    if not 0 <= model.range_min < model.range_max:
        raise UserError(f"{where}: range_min and range_max must satisfy 0 <= range_min < range_max")
    if model.noise < 0 or not 0 <= model.dropout < 1:
        raise UserError(f"{where}: noise must be >= 0 and dropout in [0, 1)")
    if model.beams > 100_000:
        raise UserError(f"{where}: {model.beams:,} beams; a 2D LiDAR has at most a few thousand (check resolution)")
    return model


def flat_lidar_options(options: dict, where: str) -> dict:
    """``options`` with a ``mount:`` mapping's keys (the mount keys or T_cam_lidar) lifted beside the
    others; a mount that is not such a mapping, or that repeats a key given beside it, is refused (the
    one would silently override the other)."""
    opts = dict(options)
    if "mount" not in opts:
        return opts
    mount = opts.pop("mount")
    if not isinstance(mount, dict):
        raise UserError(f"{where}: mount must be a mapping of {', '.join(MOUNT_KEYS)} (or T_cam_lidar), "
                        f"got {mount!r}")
    bad = sorted(str(k) for k in mount if k not in MOUNT_KEYS and k != "T_cam_lidar")
    if bad:
        raise UserError(f"{where}: {bad[0]!r} under mount: is not a mount key; use {', '.join(MOUNT_KEYS)} or "
                        "T_cam_lidar there, the others beside mount:")
    twice = sorted(str(k) for k in mount if k in opts)
    if twice:
        raise UserError(f"{where}: {twice[0]!r} is given both under mount: and beside it; keep one")
    opts.update(mount)
    return opts


def _beams(values: dict, where: str, base: LidarModel) -> tuple[float, float, float]:
    """(angle_min, angle_max, angle_increment) from ``values``: fov / resolution in degrees, or the
    radian keys a LaserScan has; both forms of one quantity at once are refused, as they would
    silently mix (fov 180 with angle_min -1 is no field of view anyone meant)."""
    limits = [k for k in ("angle_min", "angle_max") if k in values]
    if "fov" in values and limits:
        raise UserError(f"{where}: fov and {' and '.join(limits)} both give the field of view; keep fov (degrees, "
                        "centred on the LiDAR's x axis) or angle_min and angle_max (radians, as the LaserScan has "
                        "them), not both")
    if "resolution" in values and "angle_increment" in values:
        raise UserError(f"{where}: resolution and angle_increment both give the step between beams; keep "
                        "resolution (degrees) or angle_increment (radians), not both")
    if values.get("fov", 0.0) > MAX_FOV_DEG:
        raise UserError(f"{where}: fov {values['fov']:g} is more than a full turn; a 2D LiDAR sweeps at most "
                        f"{MAX_FOV_DEG:g} degrees (fov is in degrees)")
    half = math.radians(values["fov"]) / 2 if "fov" in values else None
    angle_min = values.get("angle_min", -half if half is not None else base.angle_min)
    angle_max = values.get("angle_max", half if half is not None else base.angle_max)
    step = values.get("angle_increment", math.radians(values["resolution"]) if "resolution" in values
                      else base.angle_increment)
    if not angle_min < angle_max or not 0 < step <= angle_max - angle_min:
        raise UserError(f"{where}: the beams must run from angle_min to a larger angle_max by a positive step "
                        "no larger than the field of view (fov > 0, resolution > 0)")
    if angle_max - angle_min > MAX_SPAN_RAD:
        raise UserError(f"{where}: angle_min {angle_min:g} to angle_max {angle_max:g} spans "
                        f"{math.degrees(angle_max - angle_min):.1f} degrees, more than a full turn; they are "
                        "radians (a full turn is -3.1416 to 3.1416)")
    return angle_min, angle_max, step


def read_lidar_options(path: Path) -> dict:
    """A ``lidar.yaml``'s mapping of LiDAR keys, each key once, checked as :func:`lidar_model` checks them."""
    path = Path(path)
    text = read_text(path, "LiDAR file")
    data = parse_yaml(text, str(path))   # the package's safe reading: size, nesting, alias bombs, keys twice
    if not isinstance(data, dict):
        raise UserError(f"{path}: expected a mapping of LiDAR keys ({', '.join(LIDAR_KEYS)})")
    lidar_model(data, str(path))   # checked here, so that a mistake names this file (--lidar merges the keys after)
    return data


def read_lidar_yaml(path: Path) -> LidarModel:
    """A ``lidar.yaml``: the keys of :data:`LIDAR_KEYS` (or radians and ``T_cam_lidar``)."""
    return lidar_model(read_lidar_options(path), str(path))
