"""Tiny scene folders on disk for the data tests: NeRF-synthetic and instant-ngp layouts."""

from __future__ import annotations

import json
import math
from pathlib import Path

import imageio.v3 as iio
import numpy as np


def random_c2w(rng: np.random.Generator, radius: float = 4.0) -> np.ndarray:
    """[4, 4] OpenGL camera-to-world on a sphere of ``radius`` looking at the origin."""
    p = rng.normal(size=3)
    p = radius * p / np.linalg.norm(p)
    forward = -p / radius
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    m = np.eye(4)
    m[:3] = np.stack([right, up, -forward, p], axis=1)
    return m


def random_image(rng: np.random.Generator, height: int, width: int, channels: int) -> np.ndarray:
    return rng.integers(0, 256, size=(height, width, channels), dtype=np.uint8)


def write_json(path: Path, meta) -> Path:
    path.write_text(json.dumps(meta))
    return path


def nerf_synthetic(root: Path, n_train: int = 3, n_test: int = 2, size: tuple[int, int] = (8, 6),
                   channels: int = 4, angle: float = 0.69, seed: int = 0, with_test: bool = True) -> dict:
    """A NeRF-synthetic folder: transforms_{train,test}.json with ``file_path`` without
    extension, RGBA PNGs of ``size`` = (W, H). Returns {split: (meta, [images])}."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    out = {}
    for split, n in (("train", n_train), ("test", n_test)):
        if split == "test" and not with_test:
            continue
        (root / split).mkdir(exist_ok=True)
        frames, images = [], []
        for i in range(n):
            img = random_image(rng, size[1], size[0], channels)
            iio.imwrite(root / split / f"r_{i}.png", img)
            images.append(img)
            frames.append({"file_path": f"./{split}/r_{i}", "rotation": 0.0,
                           "transform_matrix": random_c2w(rng).tolist()})
        meta = {"camera_angle_x": angle, "frames": frames}
        write_json(root / f"transforms_{split}.json", meta)
        out[split] = (meta, images)
    return out


def instant_ngp(root: Path, n: int = 7, size: tuple[int, int] = (8, 6), seed: int = 0, **top) -> tuple[dict, list]:
    """An instant-ngp folder: one transforms.json with global pinhole + distortion keys, images
    in images/ -- PNG RGBA, PNG RGB and JPG RGB, named with and without extension. ``top``
    adds or replaces top-level keys. Returns (meta, [the images as read back])."""
    rng = np.random.default_rng(seed)
    (root / "images").mkdir(parents=True, exist_ok=True)
    w, h = size
    meta = {"fl_x": 7.5, "fl_y": 7.0, "cx": 4.25, "cy": 2.75, "w": w, "h": h,
            "k1": 0.05, "k2": -0.01, "p1": 0.002, "p2": -0.001, "aabb_scale": 4, "frames": []}
    meta.update(top)
    images = []
    for i in range(n):
        kind = ("png4", "png3", "jpg")[i % 3]
        name = f"images/{i:04d}." + ("jpg" if kind == "jpg" else "png")
        iio.imwrite(root / name, random_image(rng, h, w, 4 if kind == "png4" else 3))
        images.append(iio.imread(root / name))
        file_path = name if i % 2 else name.rsplit(".", 1)[0]  # odd frames keep the extension
        meta["frames"].append({"file_path": file_path, "sharpness": 30.0,
                               "transform_matrix": random_c2w(rng).tolist()})
    write_json(root / "transforms.json", meta)
    return meta, images


def fov_to_focal(pixels: float, angle: float) -> float:
    return 0.5 * pixels / math.tan(0.5 * angle)
