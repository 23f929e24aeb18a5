"""Data sets named by specs: ``synthetic[:TRAIN[:VAL]]`` (generated, the default), ``nyu:PATH``
(Ma et al.'s h5 folder, or a CSV of RGB / 16-bit depth PNG pairs), ``kitti:PATH`` (Ma et al.'s h5
folder, or raw frames: image_2/, velodyne/, calib/), and sequences for self-supervised training
(:mod:`explorer.data.sequences`): ``synthetic-seq[:TRAIN[:VAL]]``, ``kitti-seq:DRIVE``,
``frames:FOLDER``.

Every item is a dict: ``image`` (3, H, W) float in [0, 1], ``depth`` (1, H, W) metres (0 = unknown),
``scan`` (W,) metres (0 = no return) and ``scan_row``, at the network's input size.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch.utils.data import Dataset

from explorer.data import sequences as S
from explorer.data import transforms as T
from explorer.data.lidar import ScanConfig, scan_from_image, simulate_scan
from explorer.data.readers import NYUH5, KittiH5, KittiRaw, PairCSV, RawFrame
from explorer.data.sequence_readers import FrameFolder, KittiDrive
from explorer.data.synthetic import SyntheticConfig, ensure_synthetic
from explorer.errors import UserError

__all__ = ["DataSpec", "DepthDataset", "ScanConfig", "SyntheticConfig", "open_dataset", "parse_data_spec",
           "scan_from_image", "simulate_scan"]

SPEC_HELP = ("data specs: synthetic, synthetic:TRAIN:VAL, nyu:PATH (h5 folder or CSV), kitti:PATH; "
             "sequences: synthetic-seq[:TRAIN:VAL], kitti-seq:DRIVE, frames:FOLDER")
SEQUENCE_KINDS = ("synthetic-seq", "kitti-seq", "frames")
_GENERATED_DEFAULTS = {"synthetic": (2000, 200), "synthetic-seq": (1200, 120)}
#: kinds whose training augmentation is a horizontal flip alone (FastDepth's NYU recipe also scales,
#: rotates and jitters colours): their frames can be prepared once and flipped per batch
FLIP_ONLY_KINDS = ("synthetic", "kitti")


@dataclass(frozen=True)
class DataSpec:
    kind: str          # synthetic | nyu | kitti | synthetic-seq | kitti-seq | frames
    path: str = ""
    train: int = 2000
    val: int = 200

    @property
    def is_sequence(self) -> bool:
        return self.kind in SEQUENCE_KINDS

    def __str__(self) -> str:
        if self.kind in _GENERATED_DEFAULTS:
            default = (self.train, self.val) == _GENERATED_DEFAULTS[self.kind]
            return self.kind if default else f"{self.kind}:{self.train}:{self.val}"
        return f"{self.kind}:{self.path}"


#: the most frames a generated data set may have (train and val): about 15 GB on disk at 224x224
MAX_GENERATED = 100_000


def parse_data_spec(spec: str | DataSpec) -> DataSpec:
    if isinstance(spec, DataSpec):
        return spec
    kind, _, rest = str(spec).partition(":")
    kind = kind.lower()
    if kind in _GENERATED_DEFAULTS:
        parts = [p for p in rest.split(":") if p] if rest else []
        try:
            nums = [int(p) for p in parts]
        except ValueError:
            raise UserError(f"data '{spec}': {kind} takes frame counts, e.g. {kind}:2000:200") from None
        train = nums[0] if nums else _GENERATED_DEFAULTS[kind][0]
        val = nums[1] if len(nums) > 1 else max(train // 10, 4)
        if train < 1 or val < 1:
            raise UserError(f"data '{spec}': frame counts must be positive")
        if train + val > MAX_GENERATED:
            raise UserError(f"data '{spec}': at most {MAX_GENERATED:,} generated frames in all (each is kept on "
                            "disk); use real data for more")
        return DataSpec(kind, "", train, val)
    if kind in ("nyu", "kitti", "kitti-seq", "frames"):
        if not rest:
            raise UserError(f"data '{spec}': give a path, e.g. {kind}:/data/{kind}")
        if not Path(rest).exists():
            raise UserError(f"data '{spec}': {rest} does not exist")
        return DataSpec(kind, rest)
    raise UserError(f"unknown data set '{spec}': {SPEC_HELP}")


class _SyntheticFrames:
    """A generated split held in memory as the file stores it: rgb uint8, depth float16 (each frame's
    depth made float32, the same values, when it is read): half the memory of float32 depth."""

    def __init__(self, path: Path, split: str) -> None:
        import h5py
        with h5py.File(path, "r") as f:
            self.rgb = np.asarray(f[split]["rgb"])
            self.depth = np.asarray(f[split]["depth"])

    def __len__(self) -> int:
        return len(self.rgb)

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
    def __init__(self, frames, kind: str, input_size: tuple[int, int], train: bool = False,
                 scan: ScanConfig = ScanConfig(), seed: int = 0, name: str = "") -> None:
        self.frames, self.kind, self.input_size = frames, kind, tuple(input_size)
        self.train, self.scan, self.seed, self.name = train, scan, seed, name
        self.epoch = 0

    def __len__(self) -> int:
        return len(self.frames)

    def flipped(self, i: int) -> bool:
        """Whether item ``i`` is mirrored this epoch (its generator's first draw, as ``__getitem__`` makes
        it) on data whose training augmentation is a flip alone (``FLIP_ONLY_KINDS``)."""
        return self.train and np.random.default_rng([self.seed, self.epoch, i]).random() < 0.5

    def unflipped(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, int | None]:
        """Item ``i`` at the input size before any flip: (rgb uint8 (H, W, 3), depth float32 (H, W), and
        the scan and its row where the data measured one, else None, None) for ``FLIP_ONLY_KINDS``."""
        if self.kind not in FLIP_ONLY_KINDS:
            raise ValueError(f"{self.kind} frames are augmented beyond a flip")
        rgb, depth, scan_img = self._transform(self.frames[i], None, train=False)
        if scan_img is None:
            return rgb, depth, None, None
        scan, row = scan_from_image(np.ascontiguousarray(scan_img))
        return rgb, depth, scan, row

    def _transform(self, f: RawFrame, rng: np.random.Generator | None, train: bool | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        size = self.input_size
        scan_img = f.scan_image
        train = self.train if train is None else train
        if self.kind == "nyu":
            if train:
                rgb, depth = T.nyu_train(f.rgb, f.depth, size, rng)
            else:
                rgb, depth = T.nyu_val(f.rgb, f.depth, size)
        elif self.kind == "kitti":
            rgb, depth = T.kitti_val(f.rgb, f.depth, size)
            if scan_img is not None:
                _, scan_img = T.kitti_val(f.rgb, scan_img, size)
            if train and rng.random() < 0.5:
                rgb, depth = rgb[:, ::-1], depth[:, ::-1]
                scan_img = scan_img[:, ::-1] if scan_img is not None else None
        else:
            rgb, depth = T.resize_rgb(f.rgb, size), T.resize_nearest(f.depth, size)
            if train and rng.random() < 0.5:
                rgb, depth = rgb[:, ::-1], depth[:, ::-1]
        return np.ascontiguousarray(rgb), np.ascontiguousarray(depth), scan_img

    def __getitem__(self, i: int) -> dict:
        rng = np.random.default_rng([self.seed, self.epoch, i])
        f = self.frames[i]
        rgb, depth, scan_img = self._transform(f, rng)
        if scan_img is not None:
            scan, row = scan_from_image(np.ascontiguousarray(scan_img))
        else:
            scan, row = simulate_scan(depth, self.scan, rng if (self.scan.noise or self.scan.dropout) else None)
        return {"image": torch.tensor(rgb).permute(2, 0, 1).float() / 255.0,
                "depth": torch.tensor(depth, dtype=torch.float32)[None],
                "scan": torch.tensor(scan, dtype=torch.float32), "scan_row": row}


def open_dataset(spec: str | DataSpec, split: str, input_size: tuple[int, int] = (224, 224),
                 train_augment: bool | None = None, scan: ScanConfig = ScanConfig(), seed: int = 0,
                 progress: Callable[[int, int], None] | None = None) -> DepthDataset:
    """The ``split`` ('train' or 'val') of a data set at the network's input size (a
    :class:`~explorer.data.sequences.SequenceDataset` for sequence specs)."""
    ds = parse_data_spec(spec)
    if split not in ("train", "val"):
        raise UserError(f"split must be 'train' or 'val', got {split!r}")
    if ds.is_sequence:
        return _open_sequences(ds, split, input_size, scan, seed, progress)
    augment = (split == "train") if train_augment is None else train_augment
    if ds.kind == "synthetic":
        cfg = SyntheticConfig(train=ds.train, val=ds.val)
        frames = _synthetic_frames(ensure_synthetic(cfg, progress), split)
    else:
        p = Path(ds.path)
        if ds.kind == "nyu":
            frames = PairCSV(p) if p.is_file() else NYUH5(p, split)
        elif p.is_dir() and (p / "velodyne").is_dir():
            frames = KittiRaw(p)
        else:
            frames = KittiH5(p, split)
    if scan.max_range == ScanConfig().max_range and ds.kind == "kitti":
        scan = ScanConfig(row=scan.row, points=scan.points, max_range=80.0, dropout=scan.dropout, noise=scan.noise)
    return DepthDataset(frames, ds.kind, input_size, augment, scan, seed, str(ds))


def _open_sequences(ds: DataSpec, split: str, input_size: tuple[int, int], scan: ScanConfig, seed: int,
                    progress: Callable[[int, int], None] | None):
    if ds.kind == "synthetic-seq":
        path = S.ensure_synthetic_sequences(S.SyntheticSequenceConfig(train=ds.train, val=ds.val), progress)
        source = S.SyntheticSequences(path, split)
    elif ds.kind == "kitti-seq":
        source = KittiDrive(Path(ds.path), split)
        if scan.max_range == ScanConfig().max_range:
            scan = ScanConfig(row=scan.row, points=scan.points, max_range=80.0, dropout=scan.dropout, noise=scan.noise)
    else:
        source = FrameFolder(Path(ds.path), split)
    return S.SequenceDataset(source, input_size, scan, seed, str(ds))
