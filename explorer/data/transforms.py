"""FastDepth's transforms (validation and training augmentation), on numpy frames."""

from __future__ import annotations

import numpy as np
from PIL import Image


def resize_nearest(a: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Nearest resize of (H, W) or (H, W, C) to size (H, W), as PIL's NEAREST."""
    h, w = a.shape[:2]
    rows = np.minimum((np.arange(size[0]) + 0.5) * h / size[0], h - 1).astype(int)
    cols = np.minimum((np.arange(size[1]) + 0.5) * w / size[1], w - 1).astype(int)
    return a[rows][:, cols]


def resize_rgb(rgb: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    if rgb.shape[:2] == tuple(size):
        return rgb
    return np.asarray(Image.fromarray(rgb).resize((size[1], size[0]), Image.BILINEAR))


def center_crop(a: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    h, w = a.shape[:2]
    top, left = int(round((h - size[0]) / 2.0)), int(round((w - size[1]) / 2.0))
    return a[top:top + size[0], left:left + size[1]]


def bottom_crop(a: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """KITTI (sparse-to-dense): the bottom rows, centred horizontally (the sky has no LiDAR)."""
    h, w = a.shape[:2]
    left = int(round((w - size[1]) / 2.0))
    return a[h - size[0]:, left:left + size[1]]


NYU_RESIZE_HEIGHT = 250
NYU_CROP = (228, 304)
KITTI_CROP = (228, 912)


def nyu_val(rgb: np.ndarray, depth: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Nearest resize 480x640 -> 250x333, centre crop 228x304, resize to ``size``."""
    h, w = depth.shape
    mid = (NYU_RESIZE_HEIGHT, int(w * NYU_RESIZE_HEIGHT / h))
    rgb, depth = resize_nearest(rgb, mid), resize_nearest(depth, mid)
    rgb, depth = center_crop(rgb, NYU_CROP), center_crop(depth, NYU_CROP)
    return resize_rgb(rgb, size), resize_nearest(depth, size)


def nyu_box(shape: tuple[int, int]) -> tuple[float, float, float, float]:
    """(top, left, height, width) of the source frame that :func:`nyu_val` resizes to the input size."""
    h, w = shape
    f = NYU_RESIZE_HEIGHT / h
    mid_w = int(w * f)
    top, left = int(round((NYU_RESIZE_HEIGHT - NYU_CROP[0]) / 2.0)), int(round((mid_w - NYU_CROP[1]) / 2.0))
    return top / f, left / f, NYU_CROP[0] / f, NYU_CROP[1] / f


def nyu_train(rgb: np.ndarray, depth: np.ndarray, size: tuple[int, int],
              rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """FastDepth's augmentation: scale s in [1, 1.5] (depth / s), rotation within 5 degrees,
    horizontal flip, colour jitter (0.4), then the validation crop."""
    s = rng.uniform(1.0, 1.5)
    angle = rng.uniform(-5.0, 5.0)
    flip = rng.random() < 0.5
    h, w = depth.shape
    mid = (int(NYU_RESIZE_HEIGHT * s), int(w * NYU_RESIZE_HEIGHT * s / h))
    img = Image.fromarray(rgb).rotate(angle, Image.BILINEAR).resize((mid[1], mid[0]), Image.BILINEAR)
    dep = Image.fromarray(depth.astype(np.float32)).rotate(angle, Image.NEAREST).resize((mid[1], mid[0]), Image.NEAREST)
    rgb2, depth2 = center_crop(np.asarray(img), NYU_CROP), center_crop(np.asarray(dep) / s, NYU_CROP)
    if flip:
        rgb2, depth2 = rgb2[:, ::-1], depth2[:, ::-1]
    rgb2 = color_jitter(rgb2, rng)
    return resize_rgb(np.ascontiguousarray(rgb2), size), resize_nearest(np.ascontiguousarray(depth2), size)


def color_jitter(rgb: np.ndarray, rng: np.random.Generator, amount: float = 0.4) -> np.ndarray:
    x = rgb.astype(np.float32) / 255.0
    x = x * rng.uniform(1 - amount, 1 + amount)                       # brightness
    mean = x.mean()
    x = (x - mean) * rng.uniform(1 - amount, 1 + amount) + mean        # contrast
    grey = x.mean(axis=2, keepdims=True)
    x = (x - grey) * rng.uniform(1 - amount, 1 + amount) + grey        # saturation
    return (np.clip(x, 0, 1) * 255).astype(np.uint8)


def kitti_val(rgb: np.ndarray, depth: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Bottom crop 228x912 (sparse-to-dense), then resize to ``size`` (nearest for sparse depth)."""
    crop = (min(KITTI_CROP[0], depth.shape[0]), min(KITTI_CROP[1], depth.shape[1]))
    return resize_rgb(bottom_crop(rgb, crop), size), resize_nearest(bottom_crop(depth, crop), size)
