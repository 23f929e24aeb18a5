"""Synthetic indoor scenes with exact depth: the embedded default data set (nothing downloaded).

Each scene is a room (random size) with textured floor, walls and ceiling, and boxes, cylinders and
spheres on the floor, lit by a point light (Lambertian shading), seen by a camera with NYU-like
intrinsics at a random height, pitch and yaw. Rendering is vectorised ray casting (one ray per
pixel, numpy), deterministic by seed. The image carries depth cues a network can learn beyond the
scan line: perspective texture gradients, shading, occlusion and object contact with the floor.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from explorer.errors import UserError, refused_write
from explorer.files import (Hdf5Writer, check_free_space, check_writable_folder, remove_dead_scratch,
                           writing_hdf5)

MIN_DEPTH, MAX_DEPTH = 0.5, 10.0
HFOV_DEG = 60.0  # NYU's Kinect: ~58-63 degrees


@dataclass(frozen=True)
class SyntheticConfig:
    train: int = 2000
    val: int = 200
    height: int = 224
    width: int = 224
    seed: int = 0

    @property
    def key(self) -> str:
        text = f"v1-{self.train}-{self.val}-{self.height}x{self.width}-{self.seed}"
        return hashlib.sha1(text.encode()).hexdigest()[:10]


def cache_dir() -> Path:
    root = os.environ.get("ANYTIME_EXPLORER_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME", os.path.expanduser("~/.cache")), "anytime-explorer")
    return Path(root)


#: how to go on when the cache cannot be written
CACHE_FIX = "free space there, or set ANYTIME_EXPLORER_CACHE to a folder on a disk with room"


@contextmanager
def writing_cache(path: Path, need: int, what: str) -> Iterator[Hdf5Writer]:
    """The cache file ``path`` (HDF5) written whole or not at all (:func:`explorer.files.writing_hdf5`),
    its folder tried and its disk's free space (``need`` bytes, the least the ``what`` takes) checked
    before any work; what a generation killed earlier left is removed. A disk that fills meanwhile (or a
    folder made read-only) is one line, with nothing of the file left."""
    check_writable_folder(path.parent, what, "set ANYTIME_EXPLORER_CACHE to a folder you can write", keep=False)
    check_free_space(_existing(path.parent), need, what, CACHE_FIX)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_dead_scratch(path.parent)   # what a generation killed earlier (SIGTERM, kill -9) left
    try:
        with writing_hdf5(path) as out:
            yield out
    except Exception as exc:
        refused = refused_write(exc)
        if refused is None:
            raise
        raise UserError(f"{path}: cannot write the {what} ({os.strerror(refused.errno).lower()}): {CACHE_FIX}; "
                        "nothing of it was kept") from None


def _camera_rays(h: int, w: int, yaw: float, pitch: float) -> np.ndarray:
    """World ray directions (H*W, 3) whose component along the view axis is 1, so the ray
    parameter at a hit is the z-depth."""
    f = (w / 2) / np.tan(np.radians(HFOV_DEG) / 2)
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    x, y = (u - w / 2) / f, -(v - h / 2) / f
    fwd = np.array([np.cos(pitch) * np.sin(yaw), np.cos(pitch) * np.cos(yaw), np.sin(pitch)])
    right = np.array([np.cos(yaw), -np.sin(yaw), 0.0])
    up = np.cross(right, fwd)
    return (x.reshape(-1, 1) * right + y.reshape(-1, 1) * up + fwd).astype(np.float64)


def camera_to_world(cam: np.ndarray, yaw: float, pitch: float) -> np.ndarray:
    """4x4 pose of the camera that :func:`_camera_rays` describes, in the computer-vision convention
    (x right, y down, z forward), mapping camera coordinates to world coordinates."""
    fwd = np.array([np.cos(pitch) * np.sin(yaw), np.cos(pitch) * np.cos(yaw), np.sin(pitch)])
    right = np.array([np.cos(yaw), -np.sin(yaw), 0.0])
    up = np.cross(right, fwd)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, -up, fwd], axis=1)
    pose[:3, 3] = cam
    return pose


def intrinsics(h: int, w: int) -> np.ndarray:
    """3x3 intrinsics of the rendered camera in pixel-index coordinates (pixel j's centre is at j)."""
    f = (w / 2) / np.tan(np.radians(HFOV_DEG) / 2)
    return np.array([[f, 0.0, w / 2 - 0.5], [0.0, f, h / 2 - 0.5], [0.0, 0.0, 1.0]])


def _hash_noise(p: np.ndarray, scale: float, seed: int) -> np.ndarray:
    """Cheap smooth-ish procedural noise in [0, 1] from world coordinates."""
    q = p * scale
    s = np.sin(q[:, 0] * 1.7 + seed) * np.sin(q[:, 1] * 2.3 + 2 * seed) + np.sin(q[:, 2] * 1.9 + q[:, 0] * 0.7)
    return 0.5 + 0.25 * s


@dataclass(frozen=True)
class Room:
    """One random room: its size, materials, objects and light, and the camera pose it was drawn with
    (``cam`` position, ``yaw``, ``pitch``; a sequence moves the camera away from it)."""

    size: tuple[float, float, float]
    cam: np.ndarray
    yaw: float
    pitch: float
    colours: dict
    objects: tuple
    light: np.ndarray
    power: float


def sample_room(rng: np.random.Generator) -> Room:
    """Draws a room (the draw order is part of the data: cached files and seeds depend on it)."""
    lx, ly, lz = rng.uniform(3.0, 8.0), rng.uniform(3.0, 8.0), rng.uniform(2.4, 3.2)
    cam = np.array([rng.uniform(0.6, lx - 0.6), rng.uniform(0.6, ly - 0.6), rng.uniform(0.8, 1.6)])
    yaw, pitch = rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(-20, 8))
    colours = {0: rng.uniform(0.5, 0.9, 3), 1: rng.uniform(0.5, 0.9, 3), 2: rng.uniform(0.5, 0.9, 3),
               3: rng.uniform(0.5, 0.9, 3), 4: rng.uniform(0.25, 0.6, 3), 5: np.full(3, rng.uniform(0.8, 0.95))}
    # objects standing on the floor, not too close to the camera
    objects = []
    for _ in range(rng.integers(4, 10)):
        kind = rng.choice(["box", "box", "cylinder", "sphere"])
        c = np.array([rng.uniform(0.3, lx - 0.3), rng.uniform(0.3, ly - 0.3)])
        if np.linalg.norm(c - cam[:2]) < 1.0:
            continue
        mat = 6 + len(objects)
        colours[mat] = rng.uniform(0.1, 0.95, 3)
        if kind == "box":
            half = np.array([rng.uniform(0.15, 0.8), rng.uniform(0.15, 0.8)])
            params = (half, rng.uniform(0.3, 2.0))
        elif kind == "cylinder":
            params = (rng.uniform(0.1, 0.5), rng.uniform(0.4, 1.8))
        else:
            params = (rng.uniform(0.15, 0.6),)
        objects.append((str(kind), c, mat, params))
    light = np.array([rng.uniform(0.5, lx - 0.5), rng.uniform(0.5, ly - 0.5), lz - 0.05])
    power = rng.uniform(6.0, 12.0)
    return Room((lx, ly, lz), cam, float(yaw), float(pitch), colours, tuple(objects), light, float(power))


def render_scene(rng: np.random.Generator, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """(rgb uint8 (H, W, 3), depth float32 (H, W) metres) of one random room."""
    room = sample_room(rng)
    return render_room(room, room.cam, room.yaw, room.pitch, h, w, rng)


class _Hits:
    """The nearest hit so far along each ray: its distance, surface normal and material. Surfaces
    are cast one after another; each keeps only the rays it meets nearer than any before it."""

    def __init__(self, n: int) -> None:
        self.t = np.full(n, np.inf)
        self.normal = np.zeros((n, 3))
        self.material = np.zeros(n, dtype=np.int32)

    def take(self, t: np.ndarray, nrm: np.ndarray, mat: int) -> None:
        hit = (t > 1e-6) & (t < self.t)
        self.t[hit] = t[hit]
        self.normal[hit] = nrm[hit] if nrm.ndim == 2 else nrm
        self.material[hit] = mat


def render_room(room: Room, cam: np.ndarray, yaw: float, pitch: float, h: int, w: int,
                noise_rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(rgb uint8 (H, W, 3), depth float32 (H, W) metres) of ``room`` seen from camera position
    ``cam`` looking along ``yaw``/``pitch``; ``noise_rng`` draws the sensor noise."""
    d = _camera_rays(h, w, yaw, pitch)
    hits = _Hits(d.shape[0])
    _cast_room(hits, cam, d, room.size)
    _cast_objects(hits, cam, d, room.objects)
    depth = hits.t
    p = cam + depth[:, None] * d
    albedo = np.stack([room.colours[m] for m in range(max(room.colours) + 1)])[hits.material]
    rgb = albedo * (_texture(hits.material, p) * _shading(room, p, hits.normal))[:, None]
    rgb += noise_rng.normal(0, 0.01, rgb.shape)
    rgb = (np.clip(rgb, 0, 1) * 255).astype(np.uint8).reshape(h, w, 3)
    depth = np.clip(depth, 0, MAX_DEPTH).astype(np.float32).reshape(h, w)
    depth[~np.isfinite(depth)] = MAX_DEPTH
    return rgb, depth


def _cast_room(hits: _Hits, cam: np.ndarray, d: np.ndarray, size: tuple[float, float, float]) -> None:
    """The room's interior: each ray leaves through the nearest of the three planes it points at.
    Materials 0-3 are the walls, 4 the floor, 5 the ceiling."""
    n = d.shape[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis, length in enumerate(size):
            bound = np.where(d[:, axis] > 0, length, 0.0)
            t = (bound - cam[axis]) / d[:, axis]
            nrm = np.zeros((n, 3))
            nrm[:, axis] = -np.sign(d[:, axis])
            mat = np.where(d[:, axis] > 0, 2 * axis + 1, 2 * axis)
            for m in np.unique(mat):
                hits.take(np.where(mat == m, t, np.inf), nrm, int(m))


def _cast_objects(hits: _Hits, cam: np.ndarray, d: np.ndarray, objects: tuple) -> None:
    """The objects standing on the floor, in the order drawn (a tie goes to the earlier one)."""
    cast = {"box": _cast_box, "cylinder": _cast_cylinder, "sphere": _cast_sphere}
    for kind, c, mat, params in objects:
        with np.errstate(divide="ignore", invalid="ignore"):
            cast[kind](hits, cam, d, c, mat, params)


def _cast_box(hits: _Hits, cam: np.ndarray, d: np.ndarray, c: np.ndarray, mat: int, params: tuple) -> None:
    """An axis-aligned box on the floor (slab test: the ray enters at the last of its entries)."""
    half, top = params
    n = d.shape[0]
    lo = np.array([c[0] - half[0], c[1] - half[1], 0.0])
    hi = np.array([c[0] + half[0], c[1] + half[1], top])
    t1, t2 = (lo - cam) / d, (hi - cam) / d
    tmin, tmax = np.minimum(t1, t2), np.maximum(t1, t2)
    t_near, axis = tmin.max(axis=1), tmin.argmax(axis=1)
    t = np.where((t_near <= tmax.min(axis=1)) & (t_near > 0), t_near, np.inf)
    nrm = np.zeros((n, 3))
    nrm[np.arange(n), axis] = -np.sign(d[np.arange(n), axis])
    hits.take(t, nrm, mat)


def _cast_cylinder(hits: _Hits, cam: np.ndarray, d: np.ndarray, c: np.ndarray, mat: int, params: tuple) -> None:
    """An upright cylinder on the floor: its side, then its flat top."""
    r, top = params
    oc = cam[:2] - c
    a = (d[:, :2] ** 2).sum(1)
    b = 2 * (d[:, :2] * oc).sum(1)
    disc = b * b - 4 * a * ((oc ** 2).sum() - r * r)
    t = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
    z = cam[2] + t * d[:, 2]
    t = np.where((disc > 0) & (z >= 0) & (z <= top), t, np.inf)
    p = cam[:2] + t[:, None] * d[:, :2]
    nrm = np.zeros((d.shape[0], 3))
    nrm[:, :2] = np.nan_to_num((p - c) / r)
    hits.take(t, nrm, mat)
    tc = (top - cam[2]) / d[:, 2]
    pc = cam[:2] + tc[:, None] * d[:, :2]
    tc = np.where(((pc - c) ** 2).sum(1) <= r * r, tc, np.inf)
    hits.take(tc, np.array([0.0, 0.0, 1.0]), mat)


def _cast_sphere(hits: _Hits, cam: np.ndarray, d: np.ndarray, c: np.ndarray, mat: int, params: tuple) -> None:
    """A sphere resting on the floor."""
    (r,) = params
    centre = np.array([c[0], c[1], r])
    oc = cam - centre
    b = 2 * (d * oc).sum(1)
    a = (d ** 2).sum(1)
    disc = b * b - 4 * a * ((oc ** 2).sum() - r * r)
    t = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
    p = cam + t[:, None] * d
    hits.take(t, np.nan_to_num((p - centre) / r), mat)


def _texture(material: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Brightness factor of each hit's texture: floor planks, striped walls, checkered objects. The
    patterns are fixed in the world, so they shrink with distance (a depth cue)."""
    tex = np.ones(len(material))
    floor = material == 4
    plank = (np.floor(p[:, 0] / 0.25) + np.floor(p[:, 1] / 1.2 + 0.5 * (np.floor(p[:, 0] / 0.25) % 2))) % 2
    tex[floor] = 0.75 + 0.25 * plank[floor] * _hash_noise(p[floor], 3.0, 1)
    walls = material < 4
    stripe = (np.sin(p[:, 2] * 12.0) > 0.6) | (p[:, 2] < 0.12)
    tex[walls] = np.where(stripe[walls], 0.7, 0.9 + 0.1 * _hash_noise(p[walls], 2.0, 2))
    objs = material >= 6
    checker = (np.floor(p[:, 0] / 0.15) + np.floor(p[:, 1] / 0.15) + np.floor(p[:, 2] / 0.15)) % 2
    tex[objs] = 0.8 + 0.2 * checker[objs]
    return tex


def _shading(room: Room, p: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Lambertian shading from the ceiling light, with inverse-square falloff and ambient light."""
    to_light = room.light - p
    dist = np.linalg.norm(to_light, axis=1, keepdims=True)
    lambert = np.clip((normal * to_light / np.maximum(dist, 1e-6)).sum(1), 0, 1)
    return 0.25 + 0.75 * np.clip(room.power * lambert / (1.0 + dist[:, 0] ** 2), 0, 1.3)


def _render_job(job: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    seed, index, h, w = job
    return render_scene(np.random.default_rng([seed, index]), h, w)


class _pool:
    """A process pool over the machine's cores (rendering is CPU-bound numpy), or none on one core."""

    def __enter__(self):
        import multiprocessing as mp
        n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        # not fork: a process with threads (a search's progress bar, its core monitor) can fork a worker
        # holding a lock no thread will release, and the pool then waits for it for ever. A fork server
        # forks the workers from a clean process of its own.
        method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
        self.pool = mp.get_context(method).Pool(n) if n > 1 else None
        return self.pool

    def __exit__(self, *exc) -> None:
        if self.pool is not None:
            self.pool.terminate()


def generate(config: SyntheticConfig, path: Path,
             progress: Callable[[int, int], None] | None = None) -> Path:
    """Render the train and val splits into one HDF5 file (written to a temporary name first, so an
    interrupted generation never leaves a half file behind)."""
    total, done = config.train + config.val, 0
    with writing_cache(path, _least_bytes(total, config.height, config.width), "synthetic data cache") as out:
        f = out.file
        f.attrs["config"] = repr(config)
        for split, count, offset in (("train", config.train, 0), ("val", config.val, 10_000_000)):
            g = f.create_group(split)
            rgb = g.create_dataset("rgb", (count, config.height, config.width, 3), np.uint8,
                                   chunks=(1, config.height, config.width, 3), compression="lzf")
            dep = g.create_dataset("depth", (count, config.height, config.width), np.float16,
                                   chunks=(1, config.height, config.width), compression="lzf")
            jobs = [(config.seed, offset + i, config.height, config.width) for i in range(count)]
            with _pool() as pool:
                frames = pool.imap(_render_job, jobs, chunksize=8) if pool else map(_render_job, jobs)
                for i, (im, dp) in enumerate(frames):
                    rgb[i], dep[i] = im, dp
                    out.check()   # a disk that filled: stop here, not after rendering the rest
                    done += 1
                    if progress:
                        progress(done, total)
    return path


def _existing(folder: Path) -> Path:
    """``folder``, or the nearest folder above it that exists (the disk it will be made on)."""
    return next((f for f in (folder, *folder.parents) if f.exists()), folder)


def _least_bytes(frames: int, h: int, w: int) -> int:
    """The least a cache of ``frames`` RGB frames with 16-bit depth takes: LZF rarely halves them."""
    return frames * h * w * (3 + 2) // 2


def ensure_synthetic(config: SyntheticConfig = SyntheticConfig(),
                     progress: Callable[[int, int], None] | None = None) -> Path:
    path = cache_dir() / f"synthetic-{config.key}.h5"
    if not path.is_file():
        generate(config, path, progress)
    return path
