"""Sequence data for self-supervised training: each sample is a target frame with its neighbours
(t-1, t+1), the camera intrinsics, and the relative poses when they are known.

Sources: ``synthetic-seq[:TRAIN:VAL]`` (the synthetic rooms of :mod:`explorer.data.synthetic`, the
camera moving smoothly through each one; exact depth and poses; generated once and cached),
``kitti-seq:DRIVE`` (a KITTI raw drive) and ``frames:FOLDER`` (consecutive images plus an
intrinsics file); the last two are read by :mod:`explorer.data.sequence_readers`.

An item has the keys of :class:`explorer.data.DepthDataset`'s items (``image``, ``depth`` for
evaluation, ``scan``, ``scan_row``) plus ``sources`` (2, 3, H, W): frames t-1 and t+1, ``K`` (3, 3)
at the input size in pixel-index coordinates (pixel j's centre at j), ``pose`` (2, 4, 4): the
transform from the target camera to each source camera (identity when unknown) and ``pose_known``.
"""

from __future__ import annotations

import copy

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Protocol

import numpy as np
import torch
from torch.utils.data import Dataset

from explorer.data import transforms as T
from explorer.data._scans import frame_scan
from explorer.data.lidar import ScanConfig
from explorer.scan import LidarModel, ScanPoints, scale_intrinsics  # noqa: F401  (scale_intrinsics: part of this module's face)
from explorer.data.synthetic import (
    MAX_DEPTH,
    Room,
    _least_bytes,
    _pool,
    cache_dir,
    camera_to_world,
    intrinsics,
    render_room,
    sample_room,
    writing_cache,
)

#: Frames rendered per synthetic room; the middle ones are targets (each needs both neighbours).
CLIP = 5
TARGETS_PER_CLIP = CLIP - 2


@dataclass
class SequenceSample:
    """One target with its neighbours at the source resolution: ``frames`` = [t-1, t, t+1] RGB uint8,
    ``depth`` of t (0 = unknown), optional ``scan_image`` of t (a real scan's returns), ``K`` (3, 3),
    ``poses`` = camera-to-world 4x4 of the three frames, or None."""

    frames: list[np.ndarray]
    depth: np.ndarray
    K: np.ndarray
    poses: list[np.ndarray] | None = None
    scan_image: np.ndarray | None = None
    name: str = ""
    scan_points: ScanPoints | None = None   # a real scan projected into frame t (source pixels)


class SequenceSource(Protocol):
    kind: str            # "synthetic" | "kitti" | "frames": how frames are cropped and resized
    max_depth: float     # evaluation cap (metres)

    def __len__(self) -> int: ...

    def __getitem__(self, i: int) -> SequenceSample: ...


# -- synthetic sequences --------------------------------------------------------------------------
@dataclass(frozen=True)
class SyntheticSequenceConfig:
    """``train``/``val`` count target samples; rooms hold :data:`TARGETS_PER_CLIP` targets each."""

    train: int = 1200
    val: int = 120
    height: int = 224
    width: int = 224
    seed: int = 0

    @property
    def key(self) -> str:
        text = f"seq-v2-{self.train}-{self.val}-{self.height}x{self.width}-{self.seed}-{CLIP}"
        return hashlib.sha1(text.encode()).hexdigest()[:10]


def clip_poses(rng: np.random.Generator, room: Room) -> list[tuple[np.ndarray, float, float]]:
    """Smooth camera motion centred on the room's camera: a constant step of 15-30 cm (mostly
    forward, some sideways and vertical drift: enough parallax at low resolution) and a constant turn
    of up to 3 degrees per frame; the step shrinks until every pose is clear of walls and objects."""
    step = rng.uniform(0.15, 0.30)
    heading = room.yaw + rng.uniform(-0.8, 0.8)
    direction = np.array([np.sin(heading), np.cos(heading), rng.uniform(-0.1, 0.1)])
    direction /= np.linalg.norm(direction)
    turn, tilt = np.radians(rng.uniform(-3, 3)), np.radians(rng.uniform(-0.5, 0.5))
    offsets = np.arange(CLIP) - CLIP // 2
    while step > 0.02 and not all(_clear(room, room.cam + k * step * direction) for k in offsets):
        step *= 0.7
    return [(room.cam + k * step * direction, room.yaw + k * turn, room.pitch + k * tilt) for k in offsets]


def _clear(room: Room, pos: np.ndarray, margin: float = 0.25) -> bool:
    """Whether a camera at ``pos`` is inside the room and outside every object, with a margin."""
    if any(pos[a] < margin or pos[a] > room.size[a] - margin for a in range(3)):
        return False
    for kind, c, _, params in room.objects:
        if kind == "box":
            half, top = params
            if (np.abs(pos[:2] - c) < half + margin).all() and pos[2] < top + margin:
                return False
        else:
            r = params[0]
            if np.linalg.norm(pos[:2] - c) < r + margin and pos[2] < (params[1] if kind == "cylinder" else 2 * r) + margin:
                return False
    return True


def _render_clip(job: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    seed, index, h, w = job
    rng = np.random.default_rng([seed, index])
    room = sample_room(rng)
    motion = clip_poses(np.random.default_rng([seed, index, 1]), room)
    rgbs, depths, poses = [], [], []
    for cam, yaw, pitch in motion:
        rgb, depth = render_room(room, cam, yaw, pitch, h, w, rng)
        rgbs.append(rgb)
        depths.append(depth)
        poses.append(camera_to_world(cam, yaw, pitch))
    return np.stack(rgbs), np.stack(depths), np.stack(poses)


def generate_sequences(config: SyntheticSequenceConfig, path: Path,
                       progress: Callable[[int, int], None] | None = None) -> Path:
    """Renders every clip into one HDF5 file (via a temporary name: no half file is ever left)."""
    clips = {s: -(-n // TARGETS_PER_CLIP) for s, n in (("train", config.train), ("val", config.val))}
    total, done = (clips["train"] + clips["val"]) * CLIP, 0
    h, w = config.height, config.width
    with writing_cache(path, _least_bytes(total, h, w), "synthetic sequence cache") as out:
        f = out.file
        f.attrs["config"] = repr(config)
        f.attrs["K"] = intrinsics(h, w)
        for split, offset in (("train", 0), ("val", 10_000_000)):
            g = f.create_group(split)
            g.attrs["targets"] = getattr(config, split)
            n = clips[split]
            rgb = g.create_dataset("rgb", (n, CLIP, h, w, 3), np.uint8, chunks=(1, CLIP, h, w, 3), compression="lzf")
            dep = g.create_dataset("depth", (n, CLIP, h, w), np.float16, chunks=(1, CLIP, h, w), compression="lzf")
            pos = g.create_dataset("pose", (n, CLIP, 4, 4), np.float64)
            jobs = [(config.seed, offset + i, h, w) for i in range(n)]
            with _pool() as pool:
                clips_iter = pool.imap(_render_clip, jobs, chunksize=2) if pool else map(_render_clip, jobs)
                for i, (im, dp, ps) in enumerate(clips_iter):
                    rgb[i], dep[i], pos[i] = im, dp, ps
                    out.check()   # a disk that filled: stop here, not after rendering the rest
                    done += CLIP
                    if progress:
                        progress(done, total)
    return path


def ensure_synthetic_sequences(config: SyntheticSequenceConfig = SyntheticSequenceConfig(),
                               progress: Callable[[int, int], None] | None = None) -> Path:
    path = cache_dir() / f"synthetic-seq-{config.key}.h5"
    if not path.is_file():
        generate_sequences(config, path, progress)
    return path


class SyntheticSequences:
    kind = "synthetic"
    max_depth = MAX_DEPTH

    def __init__(self, path: Path, split: str) -> None:
        import h5py
        self.split = split
        with h5py.File(path, "r") as f:
            g = f[split]
            self.count = int(g.attrs["targets"])
            self.rgb = np.asarray(g["rgb"])
            self.depth = np.asarray(g["depth"], dtype=np.float32)
            self.pose = np.asarray(g["pose"])
            self.K = np.asarray(f.attrs["K"])

    def __len__(self) -> int:
        return self.count

    def frame_names(self) -> list[str]:
        """Each split renders rooms of its own: a frame is named by its split, room and place in it."""
        clips = -(-self.count // TARGETS_PER_CLIP)
        return [f"{self.split}/{c:05d}-{t}" for c in range(clips) for t in range(CLIP)]

    def __getitem__(self, i: int) -> SequenceSample:
        clip, t = divmod(i, TARGETS_PER_CLIP)
        t += 1
        frames = [self.rgb[clip, t + d] for d in (-1, 0, 1)]
        poses = [self.pose[clip, t + d] for d in (-1, 0, 1)]
        return SequenceSample(frames, self.depth[clip, t], self.K, poses, None, f"{clip:05d}-{t}")


# -- the data set ---------------------------------------------------------------------------------
#: Garg et al.'s evaluation crop of KITTI, as fractions of the full frame (rows, then columns).
GARG_CROP = (0.40810811, 0.99189189, 0.03594771, 0.96405229)


def _crop_box(kind: str, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """(top, left, height, width) of the region that is resized to the input size."""
    h, w = shape
    if kind == "kitti":  # the bottom crop of :func:`explorer.data.transforms.kitti_val`
        ch, cw = min(T.KITTI_CROP[0], h), min(T.KITTI_CROP[1], w)
        return h - ch, int(round((w - cw) / 2.0)), ch, cw
    return 0, 0, h, w


class SequenceDataset(Dataset):
    """Sequence samples at the network's input size (see the module's docstring for the keys).

    No augmentation: a flip or crop would have to move the poses with it."""

    sequence = True

    def __init__(self, source: SequenceSource, input_size: tuple[int, int], scan: ScanConfig = ScanConfig(),
                 seed: int = 0, name: str = "", lidar: LidarModel | None = None) -> None:
        """``lidar``: the LiDAR model that simulates the scan where the source has no real one."""
        self.source, self.input_size, self.scan, self.seed, self.name = source, tuple(input_size), scan, seed, name
        self.lidar = lidar
        self.max_depth = float(source.max_depth)
        self.epoch = 0

    def __len__(self) -> int:
        return len(self.source)

    def resized(self, input_size: tuple[int, int]) -> "SequenceDataset":
        """The same samples at another input size (the source is shared, not copied)."""
        other = copy.copy(self)
        other.input_size, other.epoch = tuple(input_size), 0
        return other

    def frame_names(self) -> list[str]:
        """Every frame the samples of this split read (targets and their neighbours)."""
        return list(self.source.frame_names())

    def _fit(self, a: np.ndarray, box: tuple[int, int, int, int], sparse: bool) -> np.ndarray:
        top, left, h, w = box
        a = a[top:top + h, left:left + w]
        return T.resize_nearest(a, self.input_size) if sparse else T.resize_rgb(np.ascontiguousarray(a), self.input_size)

    def __getitem__(self, i: int) -> dict:
        s = self.source[i]
        box = _crop_box(self.source.kind, s.depth.shape)
        frames = [self._fit(f, box, sparse=False) for f in s.frames]
        depth = self._fit(s.depth, box, sparse=True).astype(np.float32)
        K = scale_intrinsics(s.K, box, self.input_size)
        scan_image = self._fit(s.scan_image, box, sparse=True) if s.scan_image is not None else None
        points = s.scan_points.transformed(box, self.input_size) if s.scan_points is not None else None
        scan, rows, row = frame_scan(depth, points=points, scan_image=scan_image, lidar=self.lidar, K=K,
                                     config=self.scan, rng=np.random.default_rng([self.seed, self.epoch, i]))
        if self.source.kind == "kitti":
            depth = depth * self._fit(_garg_mask(s.depth.shape), box, sparse=True)
        if s.poses is not None:
            inv = [np.linalg.inv(p) for p in (s.poses[0], s.poses[2])]
            pose, known = np.stack([q @ s.poses[1] for q in inv]), True
        else:
            pose, known = np.stack([np.eye(4), np.eye(4)]), False
        image = lambda a: torch.tensor(np.ascontiguousarray(a)).permute(2, 0, 1).float() / 255.0  # noqa: E731
        return {"image": image(frames[1]), "depth": torch.tensor(depth)[None],
                "scan": torch.tensor(scan, dtype=torch.float32),
                "scan_rows": torch.from_numpy(rows), "scan_row": row, "sources": torch.stack([image(frames[0]), image(frames[2])]),
                "K": torch.tensor(K, dtype=torch.float32), "pose": torch.tensor(pose, dtype=torch.float32),
                "pose_known": known}


def _garg_mask(shape: tuple[int, int]) -> np.ndarray:
    h, w = shape
    mask = np.zeros(shape, np.float32)
    r0, r1, c0, c1 = GARG_CROP
    mask[int(r0 * h):int(r1 * h), int(c0 * w):int(c1 * w)] = 1.0
    return mask
