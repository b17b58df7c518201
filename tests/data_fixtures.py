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


# ---- COLMAP models ----------------------------------------------------------------------------

COLMAP_MODEL_IDS = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1, "SIMPLE_RADIAL": 2, "RADIAL": 3, "OPENCV": 4,
                    "OPENCV_FISHEYE": 5, "FULL_OPENCV": 6, "FOV": 7}


def rotation_to_qvec(rot: np.ndarray) -> np.ndarray:
    """[4] (w, x, y, z) unit quaternion of a [3, 3] rotation (w > 0)."""
    w = math.sqrt(max(0.0, 1 + np.trace(rot))) / 2
    if w < 1e-3:  # near a half turn: go through the largest diagonal
        i = int(np.argmax(np.diag(rot)))
        j, k = (i + 1) % 3, (i + 2) % 3
        v = np.zeros(3)
        v[i] = math.sqrt(max(0.0, 1 + rot[i, i] - rot[j, j] - rot[k, k])) / 2
        v[j] = (rot[j, i] + rot[i, j]) / (4 * v[i])
        v[k] = (rot[k, i] + rot[i, k]) / (4 * v[i])
        w = (rot[k, j] - rot[j, k]) / (4 * v[i])
        q = np.array([w, *v])
        return q if w >= 0 else -q
    return np.array([w, (rot[2, 1] - rot[1, 2]) / (4 * w), (rot[0, 2] - rot[2, 0]) / (4 * w),
                     (rot[1, 0] - rot[0, 1]) / (4 * w)])


def colmap_pose(c2w_gl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP's (qvec [4], tvec [3]) world-to-camera of an OpenGL [4, 4] camera-to-world."""
    c2w_cv = c2w_gl[:3, :3] * np.array([1.0, -1.0, -1.0])
    rot = c2w_cv.T
    return rotation_to_qvec(rot), -rot @ c2w_gl[:3, 3]


def write_colmap(sparse: Path, cameras: list, images: list, xyz: np.ndarray, rgb: np.ndarray, binary: bool) -> None:
    """Write a COLMAP model: cameras [(id, model, w, h, params)], images [(id, qvec, tvec,
    camera_id, name)] (each with two 2-D points), points [P, 3] and colours [P, 3] uint8."""
    import struct

    sparse.mkdir(parents=True, exist_ok=True)
    if binary:
        data = struct.pack("<Q", len(cameras))
        for cid, model, w, h, params in cameras:
            data += struct.pack(f"<iiQQ{len(params)}d", cid, COLMAP_MODEL_IDS[model], w, h, *params)
        (sparse / "cameras.bin").write_bytes(data)
        data = struct.pack("<Q", len(images))
        for iid, q, t, cid, name in images:
            data += struct.pack("<i7di", iid, *q, *t, cid) + name.encode() + b"\0"
            data += struct.pack("<Q", 2) + struct.pack("<ddqddq", 1.5, 2.5, 0, 3.5, 4.5, -1)
        (sparse / "images.bin").write_bytes(data)
        data = struct.pack("<Q", len(xyz))
        for k, (p, c) in enumerate(zip(xyz, rgb)):
            data += struct.pack("<Q3d3BdQ", k, *p, *c, 0.5, 1) + struct.pack("<ii", 1, 0)
        (sparse / "points3D.bin").write_bytes(data)
        return
    lines = ["# Camera list", *(f"{cid} {model} {w} {h} " + " ".join(repr(float(v)) for v in params)
                                 for cid, model, w, h, params in cameras)]
    (sparse / "cameras.txt").write_text("\n".join(lines) + "\n")
    lines = ["# Image list with two lines of data per image:"]
    for k, (iid, q, t, cid, name) in enumerate(images):
        lines.append(f"{iid} " + " ".join(repr(float(v)) for v in (*q, *t)) + f" {cid} {name}")
        lines.append("" if k % 2 else "1.5 2.5 0 3.5 4.5 -1")  # an image without points leaves a blank line
    (sparse / "images.txt").write_text("\n".join(lines) + "\n")
    lines = ["# 3D point list"] + [f"{k} {p[0]!r} {p[1]!r} {p[2]!r} {c[0]} {c[1]} {c[2]} 0.5 1 0"
                                    for k, (p, c) in enumerate(zip(xyz.tolist(), rgb.tolist()))]
    (sparse / "points3D.txt").write_text("\n".join(lines) + "\n")


def colmap_scene(root: Path, model: str = "OPENCV", params=None, binary: bool = True, n: int = 5,
                 size: tuple[int, int] = (12, 10), seed: int = 0) -> dict:
    """A COLMAP folder: sparse/0 (one camera of ``model``, n images on a sphere around a point
    off the origin, in a frame rotated away from z-up, 40 points) and images/ PNGs of ``size``.
    Returns {"cameras", "images", "xyz", "c2w" (OpenGL [n, 4, 4] in COLMAP's frame)}."""
    rng = np.random.default_rng(seed)
    w, h = size
    params = params if params is not None else COLMAP_TEST_PARAMS[model]
    tilt = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    tilt *= np.linalg.det(tilt)
    c2w = []
    for _ in range(n):
        m = random_c2w(rng, radius=2.5)
        m[:3] = tilt @ m[:3]
        m[:3, 3] += [3.0, -1.0, 0.5]
        c2w.append(m)
    images = [(10 + i, *colmap_pose(m), 1, f"frame_{i:02d}.png") for i, m in enumerate(c2w)]
    xyz = rng.normal(size=(40, 3)) * 0.5 + [3.0, -1.0, 0.5]
    rgb = rng.integers(0, 256, (40, 3), dtype=np.uint8)
    cameras = [(1, model, w, h, params)]
    write_colmap(root / "sparse" / "0", cameras, images, xyz, rgb, binary)
    (root / "images").mkdir(parents=True, exist_ok=True)
    for _, _, _, _, name in images:
        iio.imwrite(root / "images" / name, random_image(rng, h, w, 3))
    return {"cameras": cameras, "images": images, "xyz": xyz, "c2w": np.stack(c2w)}


# parameters of each supported COLMAP model for a 12 x 10 image, in COLMAP's order
COLMAP_TEST_PARAMS = {
    "SIMPLE_PINHOLE": [11.0, 6.2, 4.9],
    "PINHOLE": [11.0, 10.0, 6.2, 4.9],
    "SIMPLE_RADIAL": [11.0, 6.2, 4.9, -0.08],
    "RADIAL": [11.0, 6.2, 4.9, -0.08, 0.02],
    "OPENCV": [11.0, 10.0, 6.2, 4.9, -0.08, 0.02, 0.004, -0.003],
    "OPENCV_FISHEYE": [7.0, 6.5, 6.2, 4.9, 0.05, -0.01, 0.003, -0.001],
}
