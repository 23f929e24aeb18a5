"""Readers of real data sets. Each yields raw frames: (rgb uint8 (H, W, 3), depth float32 (H, W)
metres with 0 = unknown, optional scan image (H, W): a real 2D scan's returns where it has them)."""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from explorer.scan import ScanPoints
from explorer.data.splits import SPLITS, VAL_SHARE, split_range
from explorer.errors import UserError
from explorer.files import WIDE_GREY, open_image, read_image, read_text  # noqa: F401  (the readers' image access)


@dataclass
class RawFrame:
    """``scan_image``: a real scan's returns as a sparse depth image (KITTI's ring); ``scan_points``:
    a real scan projected into the frame (:class:`explorer.scan.ScanPoints`, source pixels)."""

    rgb: np.ndarray
    depth: np.ndarray
    scan_image: np.ndarray | None = None
    name: str = ""
    scan_points: "ScanPoints | None" = None


def _check_frame(rgb: np.ndarray, depth: np.ndarray, name: str) -> None:
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise UserError(f"{name}: rgb has shape {rgb.shape}, expected (H, W, 3)")
    if depth.shape != rgb.shape[:2]:
        raise UserError(f"{name}: depth {depth.shape} and rgb {rgb.shape[:2]} differ in size")
    if not np.isfinite(depth).all():
        raise UserError(f"{name}: depth has NaN or infinite values; clean the file or mark them 0 (unknown)")
    if (depth < 0).any():
        raise UserError(f"{name}: depth has negative values")


def _numbered_rows(path: Path) -> list[tuple[int, list[str]]]:
    """The CSV's non-blank rows, each with the file's own 1-based number of the line it ends on. Read
    as it streams, so that a large binary file given by mistake is refused at its first bytes."""
    def text_lines(fh):
        for line in fh:
            if "\0" in line:   # never in text: an image, random bytes, or UTF-16 without its mark
                raise UnicodeError
            yield line
    try:
        # -sig: a spreadsheet's byte-order mark is not part of the first path
        with path.open(encoding="utf-8-sig", newline="") as fh:
            reader = csv.reader(text_lines(fh))
            return [(reader.line_num, r) for r in reader if r]
    except OSError as exc:
        raise UserError(f"{path}: cannot read ({exc.strerror})") from None
    except UnicodeError:
        raise UserError(f"{path}: not a UTF-8 text CSV of image,depth pairs (give one 'image.png,depth.png' "
                        "line per frame, saved as UTF-8)") from None
    except csv.Error as exc:
        raise UserError(f"{path}: line {reader.line_num}: not a CSV row ({exc}); give one 'image.png,depth.png' "
                        "line per frame") from None


def read_depth_png(path: Path) -> np.ndarray:
    """A depth image in millimetres as float32 metres. Only 16-bit grey is accepted: an 8-bit or colour
    file holds no millimetres (read as them, a wall 3 m away would be 3 cm)."""
    with open_image(path) as im:
        mode = im.mode
    if mode not in WIDE_GREY:
        raise UserError(f"{path}: depth must be a 16-bit PNG in millimetres (this one is "
                        f"{_MODE_NAMES.get(mode, mode)}): save it as 16-bit grey, uint16 millimetres")
    return read_image(path).astype(np.float32) / 1000.0


_MODE_NAMES = {"1": "1-bit", "L": "8-bit grey", "P": "8-bit palette", "LA": "8-bit grey with alpha",
               "RGB": "8-bit colour", "RGBA": "8-bit colour with alpha", "F": "32-bit float"}


# -- NYU Depth v2 ----------------------------------------------------------------------------------
class NYUH5:
    """Ma et al.'s layout: ``ROOT/{train,val}/<scene>/NNNNN.h5`` with ``rgb`` (3, 480, 640) uint8 and
    ``depth`` (480, 640) float metres. ROOT may also be a folder without splits: its last ``share`` of
    files (sorted, so by scene) validates, the rest trains."""

    def __init__(self, root: Path, split: str, share: float = VAL_SHARE) -> None:
        has = [s for s in SPLITS if (root / s).is_dir()]
        if has and split not in has:
            raise UserError(f"{root}: has {has[0]}/ but no {split}/ (give both splits, or a folder without "
                            "either: its last tenth validates)")
        base = root / split if has else root
        files = sorted(base.rglob("*.h5"))
        if not files:
            raise UserError(f"{base}: no .h5 files found (expected {{train,val}}/<scene>/NNNNN.h5)")
        self.files = files if has else [files[i] for i in split_range(len(files), split, str(root), share)]
        self.root = root

    def frame_names(self) -> list[str]:
        return [str(f.relative_to(self.root)) for f in self.files]

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, i: int) -> RawFrame:
        import h5py
        f = self.files[i]
        try:
            with h5py.File(f, "r") as h:
                missing = [k for k in ("rgb", "depth") if k not in h]
                if missing:
                    raise UserError(f"{f}: missing dataset(s) {missing} (expected 'rgb' and 'depth')")
                rgb = np.asarray(h["rgb"])
                depth = np.asarray(h["depth"], dtype=np.float32)
        except OSError as exc:
            raise UserError(f"{f}: unreadable HDF5 file ({exc})") from None
        if rgb.ndim == 3 and rgb.shape[0] == 3:
            rgb = np.transpose(rgb, (1, 2, 0))
        rgb = np.ascontiguousarray(rgb.astype(np.uint8))
        _check_frame(rgb, depth, str(f))
        return RawFrame(rgb, depth, None, f.stem)


class PairCSV:
    """A CSV of (image, depth) PNG pairs, paths relative to the CSV; depth 16-bit millimetres. With
    ``split``, the listing's last ``share`` validates and the rest trains; without, the CSV is one
    split whole (its own validation CSV is given), and ``other``, the other split's CSV, must share
    no image with it."""

    def __init__(self, path: Path, split: str | None = None, share: float = VAL_SHARE,
                 other: Path | None = None) -> None:
        self.pairs = self._read(path)
        if split is not None:
            self.pairs = [self.pairs[i] for i in split_range(len(self.pairs), split, str(path), share)]
        if other is not None:
            shared = {p.resolve() for p, _ in self.pairs} & {p.resolve() for p, _ in self._read(other)}
            if shared:
                raise UserError(f"{path} and {other} both list {sorted(shared)[0].name} (and {len(shared) - 1} more): "
                                "a validation frame must never train")

    def frame_names(self) -> list[str]:
        return [str(img.resolve()) for img, _ in self.pairs]

    @staticmethod
    def _read(path: Path) -> list[tuple[Path, Path]]:
        root = path.parent
        rows = _numbered_rows(path)
        if rows and not rows[0][1][0].lower().endswith((".png", ".jpg", ".jpeg")):
            rows = rows[1:]  # header
        if not rows:
            raise UserError(f"{path}: no image/depth pairs listed")
        bad = [n for n, r in rows if len(r) < 2 or not r[0].strip() or not r[1].strip()]
        if bad:
            raise UserError(f"{path}: line {bad[0]} does not have two columns (image, depth)")
        return [(root / r[0].strip(), root / r[1].strip()) for _, r in rows]

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, i: int) -> RawFrame:
        img_path, depth_path = self.pairs[i]
        for p in (img_path, depth_path):
            if not p.is_file():
                raise UserError(f"{p}: listed in the CSV but missing")
        try:
            rgb = read_image(img_path, "RGB")
            depth = read_depth_png(depth_path)
        except (OSError, ValueError) as exc:
            raise UserError(f"{img_path.name}/{depth_path.name}: unreadable image ({exc})") from None
        _check_frame(rgb, depth, str(img_path))
        return RawFrame(rgb, depth, None, img_path.stem)


# -- KITTI ---------------------------------------------------------------------------------------
def read_calib(path: Path) -> dict[str, np.ndarray]:
    """An object-detection calibration file: ``P2`` (3x4), ``R0_rect`` (3x3) and ``Tr_velo_to_cam``
    (3x4, rigid), each checked and reshaped."""
    out = {}
    for line in read_text(path, 'calibration file').splitlines():
        if ":" in line:
            k, v = line.split(":", 1)
            try:
                out[k.strip()] = np.array([float(x) for x in v.split()])
            except ValueError:
                raise UserError(f"{path}: malformed calibration line '{k}'") from None
    calib = {k: calib_matrix(out, k, shape, path)
             for k, shape in (("P2", (3, 4)), ("R0_rect", (3, 3)), ("Tr_velo_to_cam", (3, 4)))}
    check_projection(calib["P2"], path, "P2")
    check_rotation(calib["R0_rect"], path, "R0_rect")
    check_rotation(calib["Tr_velo_to_cam"][:, :3], path, "Tr_velo_to_cam")
    return calib


def calib_matrix(values: dict[str, np.ndarray], key: str, shape: tuple[int, ...], path: Path) -> np.ndarray:
    """``values[key]`` as a finite matrix of ``shape``, or one line naming the file, the key and the count
    it needs."""
    if key not in values:
        raise UserError(f"{path}: calibration lacks {key}")
    v, need = values[key], int(np.prod(shape))
    if v.size != need:
        what = f"a {shape[0]}x{shape[1]} matrix, row by row" if len(shape) == 2 else "a vector"
        raise UserError(f"{path}: {key} has {v.size} number(s), needs {need} ({what})")
    if not np.isfinite(v).all():
        raise UserError(f"{path}: {key} has NaN or infinite values")
    return v.reshape(shape)


def check_rotation(r: np.ndarray, path: Path, key: str) -> None:
    """A calibration's rotation must be one: a scaled or mirrored matrix moves every point to a wrong
    depth, past the range or behind the camera. The tolerance admits a file's rounding of its values."""
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-3) or np.linalg.det(r) <= 0:
        raise UserError(f"{path}: {key} is not a rigid transform (its rotation part must be orthonormal with "
                        "determinant +1): check the calibration file")


def check_projection(p: np.ndarray, path: Path, key: str) -> None:
    """A rectified camera's 3x4 projection must have positive focal lengths and map depth to its third
    row: with a zero focal length every point lands on one column, or divides by zero."""
    if not (p[0, 0] > 0 and p[1, 1] > 0 and p[2, 2] > 0):
        raise UserError(f"{path}: {key} is not a camera projection (its focal lengths fx = {p[0, 0]:g}, "
                        f"fy = {p[1, 1]:g} and its [2, 2] = {p[2, 2]:g} must be positive): check the calibration file")


def read_velodyne(path: Path) -> np.ndarray:
    """A Velodyne scan as (N, 4) float32 x, y, z, reflectance, N >= 1; a file that is empty or cut
    short (not whole 16-byte records) is refused rather than read as garbage or as no points."""
    try:
        size = path.stat().st_size
        if size and size % 16 == 0:
            return np.fromfile(path, dtype=np.float32).reshape(-1, 4)
    except OSError as exc:
        raise UserError(f"{path}: cannot read the Velodyne scan ({exc.strerror})") from None
    raise UserError(f"{path}: a truncated or empty Velodyne scan ({size} bytes): expected float32 x, y, z, "
                    "reflectance records of 16 bytes each")


def project_velodyne(points: np.ndarray, calib: dict[str, np.ndarray], shape: tuple[int, int]
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Image columns, rows and depths of the points in front of the camera and inside the image
    (``calib`` as :func:`read_calib` returns it)."""
    p2 = calib["P2"]
    r0 = np.eye(4)
    r0[:3, :3] = calib["R0_rect"]
    tr = np.eye(4)
    tr[:3, :4] = calib["Tr_velo_to_cam"]
    xyz1 = np.c_[points[:, :3], np.ones(len(points))]
    cam = r0 @ tr @ xyz1.T
    front = cam[2] > 0.5
    img = p2 @ cam[:, front]
    u, v, z = img[0] / img[2], img[1] / img[2], cam[2, front]
    inside = (u >= 0) & (u < shape[1]) & (v >= 0) & (v < shape[0])
    return u[inside].astype(int), v[inside].astype(int), z[inside]


def sparse_depth(u: np.ndarray, v: np.ndarray, z: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    depth = np.zeros(shape, dtype=np.float32)
    order = np.argsort(-z)  # nearest point wins where several land on one pixel
    depth[v[order], u[order]] = z[order]
    return depth


def ring_mask(points: np.ndarray, elevation_deg: float, tolerance_deg: float = 0.2) -> np.ndarray:
    """Points of the laser ring nearest ``elevation_deg`` (a 2D LiDAR's single scan plane)."""
    elev = np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])))
    target = elev[np.argmin(np.abs(elev - elevation_deg))]
    return np.abs(elev - target) <= tolerance_deg


class KittiRaw:
    """``ROOT/image_2/*.png``, ``ROOT/velodyne/*.bin`` (float32 x, y, z, reflectance) and
    ``ROOT/calib/*.txt``: ground truth is the projected point cloud; the 2D LiDAR is the ring nearest
    ``elevation_deg`` (0 = level with the sensor). Frames in name order: the last ``share`` validates,
    one frame left out before it."""

    def __init__(self, root: Path, split: str = "train", share: float = VAL_SHARE, elevation_deg: float = 0.0) -> None:
        self.root, self.elevation = root, elevation_deg
        for sub in ("image_2", "velodyne", "calib"):
            if not (root / sub).is_dir():
                raise UserError(f"{root}: missing folder {sub}/ (expected image_2/, velodyne/, calib/)")
        names = sorted(p.stem for p in (root / "image_2").glob("*.png"))
        if not names:
            raise UserError(f"{root / 'image_2'}: no .png frames")
        self.names = [names[i] for i in split_range(len(names), split, str(root), share, gap=1)]

    def frame_names(self) -> list[str]:
        return list(self.names)

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, i: int) -> RawFrame:
        n = self.names[i]
        img, velo, cal = (self.root / "image_2" / f"{n}.png", self.root / "velodyne" / f"{n}.bin",
                          self.root / "calib" / f"{n}.txt")
        for p in (velo, cal):
            if not p.is_file():
                raise UserError(f"{p}: missing for frame {n}")
        rgb = read_image(img, "RGB")
        points = read_velodyne(velo)
        calib = read_calib(cal)
        shape = rgb.shape[:2]
        depth = sparse_depth(*project_velodyne(points, calib, shape), shape)
        ring = points[ring_mask(points, self.elevation)]
        scan_image = sparse_depth(*project_velodyne(ring, calib, shape), shape)
        return RawFrame(rgb, depth, scan_image, n)


class KittiH5(NYUH5):
    """Ma et al.'s KITTI layout: ``{train,val}/<drive>/*.h5`` with ``rgb`` and sparse ``depth``."""
