"""Data sets named by specs: ``synthetic[:TRAIN[:VAL]]`` (generated, the default), ``nyu:PATH``
(Ma et al.'s h5 folder, or a CSV of RGB / 16-bit depth PNG pairs), ``kitti:PATH`` (Ma et al.'s h5
folder, or raw frames: image_2/, velodyne/, calib/), and sequences for self-supervised training
(:mod:`explorer.data.sequences`): ``synthetic-seq[:TRAIN[:VAL]]``, ``kitti-seq:DRIVE``,
``frames:FOLDER``.

Every item is a dict: ``image`` (3, H, W) float in [0, 1], ``depth`` (1, H, W) metres (0 = unknown),
``scan`` (W,) metres (0 = no return), ``scan_rows`` (W,) the image row of each column's return
(interpolated where a column has none) and ``scan_row`` (their median: the row the network's ECU
crops around), at the network's input size. The scan is the data's own where it has one (a ROS
bag's, a folder's ``scans/``, KITTI's ring), else simulated: by the spec's LiDAR model
(:mod:`explorer.scan`) where it gives one, else the paper's ideal centre row.
"""

from __future__ import annotations

import copy
import weakref
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch.utils.data import Dataset

from explorer.data import sequences as S
from explorer.data import transforms as T
from explorer.data._scans import frame_scan
from explorer.data.lidar import ScanConfig, scan_from_image, simulate_scan
from explorer.data.readers import NYUH5, KittiH5, KittiRaw, PairCSV, RawFrame
from explorer.scan import LidarModel, read_intrinsics
from explorer.data.sequence_readers import FrameFolder, KittiDrive
from explorer.data.spec import (
    MAX_GENERATED,
    SEQUENCE_KINDS,
    SPEC_HELP,
    DataSpec,
    parse_data_spec,
    with_lidar,
)
from explorer.data.splits import VAL_SHARE, parse_share
from explorer.data.synthetic import SyntheticConfig, ensure_synthetic, intrinsics
from explorer.errors import UserError

__all__ = ["DEPTH_METRICS", "MAX_GENERATED", "MAYBE_WITHOUT_DEPTH", "SCORES", "SEQUENCE_KINDS", "SPEC_HELP",
           "DataSpec", "DepthDataset", "ScanConfig", "SyntheticConfig", "default_metric", "frames_for_downscale",
           "has_depth", "open_dataset", "parse_data_spec", "require_scores", "scan_from_image", "simulate_scan",
           "with_lidar"]

#: kinds whose training augmentation is a horizontal flip alone (FastDepth's NYU recipe also scales,
#: rotates and jitters colours): their frames can be prepared once and flipped per batch
FLIP_ONLY_KINDS = ("synthetic", "kitti")
#: NYU Depth v2's colour camera (Kinect, 640x480), in pixel-index coordinates: for simulated scans
NYU_K = np.array([[518.857901, 0.0, 325.582449], [0.0, 519.469611, 253.736166], [0.0, 0.0, 1.0]])


class _SyntheticFrames:
    """A generated split held in memory as the file stores it: rgb uint8, depth float16 (each frame's
    depth made float32, the same values, when it is read): half the memory of float32 depth."""

    def __init__(self, path: Path, split: str) -> None:
        import h5py
        self.split = split
        with h5py.File(path, "r") as f:
            self.rgb = np.asarray(f[split]["rgb"])
            self.depth = np.asarray(f[split]["depth"])

    def __len__(self) -> int:
        return len(self.rgb)

    def frame_names(self) -> list[str]:
        """Each split is rendered from scenes of its own: a frame is named by its split and index."""
        return [f"{self.split}/{i:05d}" for i in range(len(self.rgb))]

    def __getitem__(self, i: int) -> RawFrame:
        return RawFrame(self.rgb[i], self.depth[i].astype(np.float32), None, f"{i:05d}")


#: the generated splits in memory, by (file, its modification time, split): a search opens the training
#: split at the training and at the deployment size, in several places at once, and each data set
#: reads this one copy of its frames (about 0.5 GB for the default training split), released with
#: the last of them
_LOADED: "weakref.WeakValueDictionary[tuple, _SyntheticFrames]" = weakref.WeakValueDictionary()


def _synthetic_frames(path: Path, split: str) -> _SyntheticFrames:
    key = (str(path.resolve()), path.stat().st_mtime_ns, split)
    frames = _LOADED.get(key)
    if frames is None:
        frames = _LOADED[key] = _SyntheticFrames(path, split)
    return frames


class DepthDataset(Dataset):
    """Frames at the network's input size. ``K``: the frames' intrinsics at their own size (for a
    LiDAR model's simulated scan); ``lidar``: that model (None: the paper's ideal centre row)."""

    def __init__(self, frames, kind: str, input_size: tuple[int, int], train: bool = False,
                 scan: ScanConfig = ScanConfig(), seed: int = 0, name: str = "",
                 lidar: LidarModel | None = None, K: np.ndarray | None = None) -> None:
        self.frames, self.kind, self.input_size = frames, kind, tuple(input_size)
        self.train, self.scan, self.seed, self.name = train, scan, seed, name
        self.lidar, self.K = lidar, K
        self.epoch = 0

    def __len__(self) -> int:
        return len(self.frames)

    def resized(self, input_size: tuple[int, int]) -> "DepthDataset":
        """The same frames at another input size (the frames themselves are shared, not copied)."""
        other = copy.copy(self)
        other.input_size, other.epoch = tuple(input_size), 0
        return other

    def frame_names(self) -> list[str]:
        """The frames this split serves, by name (unique within a source)."""
        names = getattr(self.frames, "frame_names", None)
        return list(names()) if names else [self.frames[i].name for i in range(len(self.frames))]

    def flipped(self, i: int) -> bool:
        """Whether item ``i`` is mirrored this epoch (its generator's first draw, as ``__getitem__`` makes
        it) on data whose training augmentation is a flip alone (``FLIP_ONLY_KINDS``)."""
        return self.train and np.random.default_rng([self.seed, self.epoch, i]).random() < 0.5

    def unflipped(self, i: int):
        """Item ``i`` at the input size before any flip: (rgb uint8 (H, W, 3), depth float32 (H, W), and
        the scan, its row and each column's row where the data measured one, else None, None, None) for
        ``FLIP_ONLY_KINDS``."""
        if self.kind not in FLIP_ONLY_KINDS:
            raise ValueError(f"{self.kind} frames are augmented beyond a flip")
        rgb, depth, scan_img, _, _ = self._transform(self.frames[i], None, train=False)
        if scan_img is None:
            return rgb, depth, None, None, None
        scan, rows, row = frame_scan(depth, scan_image=scan_img)
        return rgb, depth, scan, row, rows

    def _transform(self, f: RawFrame, rng: np.random.Generator | None, train: bool | None = None):
        """(rgb, depth, scan image, the crop box that was resized to the input size, mirrored or not)."""
        size = self.input_size
        scan_img = f.scan_image
        train = self.train if train is None else train
        box, flip = (0, 0, *f.depth.shape), False
        if self.kind == "nyu":
            box = T.nyu_box(f.depth.shape)
            if train:   # its own flip, rotation and zoom: a simulated scan sees the augmented frame
                rgb, depth = T.nyu_train(f.rgb, f.depth, size, rng)
            else:
                rgb, depth = T.nyu_val(f.rgb, f.depth, size)
        elif self.kind == "kitti":
            rgb, depth = T.kitti_val(f.rgb, f.depth, size)
            if scan_img is not None:
                _, scan_img = T.kitti_val(f.rgb, scan_img, size)
            if train and rng.random() < 0.5:
                rgb, depth, flip = rgb[:, ::-1], depth[:, ::-1], True
                scan_img = scan_img[:, ::-1] if scan_img is not None else None
        else:
            rgb, depth = T.resize_rgb(f.rgb, size), T.resize_nearest(f.depth, size)
            if train and rng.random() < 0.5:
                rgb, depth, flip = rgb[:, ::-1], depth[:, ::-1], True
        return np.ascontiguousarray(rgb), np.ascontiguousarray(depth), scan_img, box, flip

    def __getitem__(self, i: int) -> dict:
        rng = np.random.default_rng([self.seed, self.epoch, i])
        f = self.frames[i]
        rgb, depth, scan_img, box, flip = self._transform(f, rng)
        points = f.scan_points.transformed(box, self.input_size, flip) if f.scan_points is not None else None
        K = S.scale_intrinsics(self.K, box, self.input_size) if self.K is not None else None
        scan, rows, row = frame_scan(depth, points=points, scan_image=scan_img, lidar=self.lidar, K=K,
                                     config=self.scan, rng=rng, flipped=flip)
        return {"image": torch.tensor(rgb).permute(2, 0, 1).float() / 255.0,
                "depth": torch.tensor(depth, dtype=torch.float32)[None],
                "scan": torch.tensor(scan, dtype=torch.float32), "scan_rows": torch.from_numpy(rows),
                "scan_row": row}


def frames_for_downscale(dataset, downscale: int):
    """The frames a network that works at 1/``downscale`` of its input trains or is scored on where
    ``dataset``'s size is asked for: the same frames, ``downscale`` times larger, so that every network
    of a study works at the size asked for (a network fed the frames as they are would work at a
    fraction of it, and learn less than it can)."""
    if downscale == 1 or not len(dataset):
        return dataset
    h, w = dataset.input_size
    return dataset.resized((h * downscale, w * downscale))


def open_dataset(spec: str | DataSpec, split: str, input_size: tuple[int, int] = (224, 224),
                 train_augment: bool | None = None, scan: ScanConfig = ScanConfig(), seed: int = 0,
                 progress: Callable[[int, int], None] | None = None) -> DepthDataset:
    """The ``split`` ('train' or 'val') of a data set at the network's input size (a
    :class:`~explorer.data.sequences.SequenceDataset` for sequence specs). The two splits of a source
    never share a frame (:mod:`explorer.data.splits`)."""
    ds = parse_data_spec(spec)
    if split not in ("train", "val"):
        raise UserError(f"split must be 'train' or 'val', got {split!r}")
    if ds.is_sequence:
        return _open_sequences(ds, split, input_size, scan, seed, progress)
    augment = (split == "train") if train_augment is None else train_augment
    frames, K = _frames(ds, split, progress)
    lidar = ds.lidar
    if lidar is not None and K is None and ds.kind != "rosbag":
        raise UserError(f"data '{ds}': a LiDAR model needs the camera's intrinsics; write them to "
                        f"{Path(ds.path).parent / 'intrinsics.txt'} (fx fy cx cy, in pixels of the images)")
    if scan.max_range == ScanConfig().max_range and ds.kind == "kitti":
        scan = ScanConfig(row=scan.row, points=scan.points, max_range=80.0, dropout=scan.dropout, noise=scan.noise)
    return DepthDataset(frames, ds.kind, input_size, augment, scan, seed, str(ds), lidar, K)


#: kinds whose frames may come without depth (a recording or a folder of frames): every other kind has it
MAYBE_WITHOUT_DEPTH = ("rosbag-seq", "frames")
#: how each path is scored on data with depth, and where there is none (camera motion known)
DEPTH_METRICS = ("rmse", "mae", "rel")
SCORES = DEPTH_METRICS + ("photometric",)


def has_depth(dataset, frames: int = 4) -> bool:
    """Whether the first ``frames`` of ``dataset`` hold some depth."""
    return any(bool((dataset[i]["depth"] > 0).any()) for i in range(min(frames, len(dataset))))


def default_metric(spec: str | DataSpec) -> str:
    """How a study on ``spec`` scores its paths unless told: RMSE against depth, or, on a recording or
    folder whose validation frames have none, the photometric error of warping the neighbouring frames
    with the camera's motion (:func:`explorer.training.selfsup.photometric_score`)."""
    ds = parse_data_spec(spec)
    if ds.kind in MAYBE_WITHOUT_DEPTH and not has_depth(open_dataset(ds, "val", (32, 32), train_augment=False)):
        return "photometric"
    return "rmse"


def require_scores(dataset, spec: str, metric: str, frames: int = 4, instead: str = "") -> None:
    """A :class:`UserError` unless the validation frames of ``dataset`` can score every path by
    ``metric``: depth for a depth metric; neighbouring frames and the camera's motion between them
    (given by the data, or measured by the LiDAR) for ``photometric``. ``instead``: what else the
    command can do without depth, said in the error."""
    if metric in DEPTH_METRICS:
        if has_depth(dataset, frames):
            return
        raise UserError(f"data '{spec}': its validation frames have no depth to measure each path's {metric} on; "
                        f"{instead}record a depth topic (rosbag: depth=TOPIC) or give depth/ (frames:)")
    if getattr(dataset, "sequence", False):
        if any(bool(dataset[i]["pose_known"]) for i in range(len(dataset))):
            return
        raise UserError(f"data '{spec}': --metric photometric needs the camera's motion between validation "
                        "frames, and none could be measured: its LiDAR scans do not match from frame to frame "
                        "(give poses.txt with frames:, or record depth and use --metric rmse)")
    raise UserError(f"data '{spec}': --metric photometric scores paths by warping neighbouring frames: give "
                    "a sequence (rosbag-seq:, frames:, synthetic-seq, kitti-seq:) or use --metric rmse")


def _frames(ds: DataSpec, split: str, progress) -> tuple[object, np.ndarray | None]:
    """The split's raw frames and their intrinsics at the frames' own size (None where unknown)."""
    share = _share(ds)
    if ds.kind == "synthetic":
        cfg = SyntheticConfig(train=ds.train, val=ds.val)
        return _synthetic_frames(ensure_synthetic(cfg, progress), split), intrinsics(cfg.height, cfg.width)
    p = Path(ds.path)
    if ds.kind == "rosbag":
        from explorer.data.rosbag import BagFrames
        frames = BagFrames(p, _bag_options(ds), split)
        return frames, frames.K
    if ds.kind == "nyu" and p.is_file():
        val = ds.val_option
        own_val = val is not None and Path(val).is_file()
        frames = PairCSV(Path(val) if own_val and split == "val" else p, None if own_val else split, share,
                         other=(p if split == "val" else Path(val)) if own_val else None)
        K_file = p.parent / "intrinsics.txt"
        return frames, (read_intrinsics(K_file) if K_file.is_file() else None)
    if ds.kind == "nyu":
        return NYUH5(p, split, share), NYU_K
    if p.is_dir() and (p / "velodyne").is_dir():
        return KittiRaw(p, split, share), None
    return KittiH5(p, split, share), None


def _share(ds: DataSpec) -> float:
    val = ds.val_option
    if val is None or (ds.kind == "nyu" and Path(val).is_file()):
        return VAL_SHARE
    return parse_share(val, f"data '{ds}'")


def _bag_options(ds: DataSpec) -> dict[str, str]:
    return dict(ds.options)


def _open_sequences(ds: DataSpec, split: str, input_size: tuple[int, int], scan: ScanConfig, seed: int,
                    progress: Callable[[int, int], None] | None):
    share = _share(ds)
    if ds.kind == "synthetic-seq":
        path = S.ensure_synthetic_sequences(S.SyntheticSequenceConfig(train=ds.train, val=ds.val), progress)
        source = S.SyntheticSequences(path, split)
    elif ds.kind == "kitti-seq":
        source = KittiDrive(Path(ds.path), split, share=share)
        if scan.max_range == ScanConfig().max_range:
            scan = ScanConfig(row=scan.row, points=scan.points, max_range=80.0, dropout=scan.dropout, noise=scan.noise)
    elif ds.kind == "rosbag-seq":
        from explorer.data.rosbag import BagSequence
        source = BagSequence(Path(ds.path), _bag_options(ds), split)
    else:
        source = FrameFolder(Path(ds.path), split, share, ds.lidar)
    return S.SequenceDataset(source, input_size, scan, seed, str(ds), None if ds.kind == "rosbag-seq" else ds.lidar)
