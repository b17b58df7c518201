"""Write a NeRF-synthetic folder as the captures people bring, with exact ground truth.

Each form holds the same views, composited over a background, with no test split (``load_scene``
holds out every 8th frame, sorted by name):

* ``colmap``: a COLMAP text model (``sparse/0/{cameras,images,points3D}.txt``, one PINHOLE
  camera, no sparse points) beside ``images/`` composited on white;
* ``colmap-sky``: the same composited over the unbounded scene's environment at infinity
  (mountains under a skyline, a sky gradient: :func:`ngp_warp.data.scene_unbounded.environment_colours`),
  so the background is textured and view-dependent in position, not trivially white;
* ``ngp``: one instant-ngp ``transforms.json`` (``camera_angle_x``, the frames' matrices) beside
  ``images/`` composited on white.

An opaque folder (the unbounded scene) is written as it is, its background already in the images.

Usage: ``python benchmarks/capture_scenes.py SRC DST --form colmap [--every 2]``.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

FORMS = ("colmap", "colmap-sky", "ngp", "nerf-synthetic")
HELD_OUT_EVERY = 8  # the loaders hold out every 8th frame (by name) of a capture without a test split


def synthetic_views(src: Path, every: int = 1) -> list[tuple[Path, np.ndarray, float]]:
    """[(image path, [4, 4] float64 OpenGL camera-to-world, camera_angle_x)] of a NeRF-synthetic
    folder's train then test frames, every ``every``-th of each split."""
    views = []
    for split in ("train", "test"):
        path = src / f"transforms_{split}.json"
        if not path.is_file():
            continue
        meta = json.loads(path.read_text())
        for frame in meta["frames"][::every]:
            image = (src / frame["file_path"]).with_suffix(".png")
            views.append((image, np.asarray(frame["transform_matrix"], dtype=np.float64), meta["camera_angle_x"]))
    return views


def ray_directions(c2w: np.ndarray, width: int, height: int, focal: float) -> np.ndarray:
    """[H, W, 3] float32 unit world directions through the pixel centres of a pinhole camera
    (OpenGL: x right, y up, looking down -z) with principal point at the image centre."""
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    cam = np.stack([(u - width / 2) / focal, -(v - height / 2) / focal, -np.ones_like(u)], -1)
    d = cam @ c2w[:3, :3].T
    return (d / np.linalg.norm(d, axis=-1, keepdims=True)).astype(np.float32)


def composite(rgba: np.ndarray, background: np.ndarray) -> np.ndarray:
    """[H, W, 3] uint8: straight-alpha ``rgba`` [H, W, 4] uint8 over ``background`` [H, W, 3]
    float in [0, 1] (opaque images are returned as they are)."""
    if rgba.shape[-1] == 3:
        return rgba
    alpha = rgba[..., 3:].astype(np.float32) / 255.0
    out = rgba[..., :3].astype(np.float32) / 255.0 * alpha + background * (1.0 - alpha)
    return (out * 255.0 + 0.5).clip(0, 255).astype(np.uint8)


def qvec_of(rotation: np.ndarray) -> np.ndarray:
    """[4] float64 unit quaternion (w, x, y, z) of a [3, 3] rotation, w ≥ 0 (COLMAP's order)."""
    m = rotation
    w = math.sqrt(max(0.0, 1.0 + m[0, 0] + m[1, 1] + m[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1.0 + m[0, 0] - m[1, 1] - m[2, 2])) / 2, m[2, 1] - m[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1.0 - m[0, 0] + m[1, 1] - m[2, 2])) / 2, m[0, 2] - m[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1.0 - m[0, 0] - m[1, 1] + m[2, 2])) / 2, m[1, 0] - m[0, 1])
    q = np.array([w, x, y, z])
    return q / np.linalg.norm(q)


def colmap_image_line(image_id: int, c2w: np.ndarray, name: str) -> str:
    """One images.txt record: COLMAP's world-to-camera (OpenCV axes) of an OpenGL camera-to-world."""
    rotation = (c2w[:3, :3] * np.array([1.0, -1.0, -1.0])).T
    t = -rotation @ c2w[:3, 3]
    return f"{image_id} " + " ".join(f"{v:.17g}" for v in (*qvec_of(rotation), *t)) + f" 1 {name}\n\n"


def write_capture(src: Path, dst: Path, form: str, every: int = 1) -> Path:
    """Write the NeRF-synthetic folder ``src`` as the capture ``form`` (one of :data:`FORMS`) at
    ``dst`` (created; must not exist). Returns ``dst``."""
    if form not in FORMS:
        raise ValueError(f"form must be one of {', '.join(FORMS)}, got {form!r}")
    views = synthetic_views(src, every)
    if form == "nerf-synthetic":
        return _write_nerf_synthetic(views, dst)
    (dst / "images").mkdir(parents=True)
    height, width = iio.imread(views[0][0]).shape[:2]
    focal = 0.5 * width / math.tan(0.5 * views[0][2])
    lines, frames = [], []
    for k, (image_path, c2w, _) in enumerate(views):
        name = f"{k:04d}.png"
        background = np.ones((height, width, 3), np.float32)
        if form == "colmap-sky":
            from ngp_warp.data.scene_unbounded import environment_colours

            d = torch.from_numpy(ray_directions(c2w, width, height, focal).reshape(-1, 3))
            d = d.cuda() if torch.cuda.is_available() else d
            background = environment_colours(d).cpu().numpy().reshape(height, width, 3)
        iio.imwrite(dst / "images" / name, composite(iio.imread(image_path), background))
        lines.append(colmap_image_line(k + 1, c2w, name))
        frames.append({"file_path": f"images/{name}", "transform_matrix": c2w.tolist()})
    if form == "ngp":
        meta = {"camera_angle_x": views[0][2], "w": width, "h": height, "frames": frames}
        (dst / "transforms.json").write_text(json.dumps(meta, indent=1))
        return dst
    sparse = dst / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text(f"1 PINHOLE {width} {height} {focal!r} {focal!r} {width / 2!r} {height / 2!r}\n")
    (sparse / "images.txt").write_text("".join(lines))
    (sparse / "points3D.txt").write_text("")
    return dst


def _write_nerf_synthetic(views: list, dst: Path) -> Path:
    """The views as a NeRF-synthetic folder (RGBA images, scored over white) whose test split is
    the frames a capture form holds out: the same training views and held-out views."""
    for split in ("train", "test"):
        (dst / split).mkdir(parents=True)
    frames = {"train": [], "test": []}
    for k, (image_path, c2w, _) in enumerate(views):
        split = "test" if k % HELD_OUT_EVERY == 0 else "train"
        (dst / split / f"{k:04d}.png").write_bytes(image_path.read_bytes())
        frames[split].append({"file_path": f"./{split}/{k:04d}", "transform_matrix": c2w.tolist()})
    for split, listed in frames.items():
        meta = {"camera_angle_x": views[0][2], "frames": listed}
        (dst / f"transforms_{split}.json").write_text(json.dumps(meta, indent=1))
    return dst


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("src", type=Path, help="a NeRF-synthetic folder (transforms_train.json, ...)")
    parser.add_argument("dst", type=Path, help="the capture folder to write (must not exist)")
    parser.add_argument("--form", choices=FORMS, default="colmap")
    parser.add_argument("--every", type=int, default=1, help="keep every n-th view of each split")
    args = parser.parse_args()
    print(write_capture(args.src, args.dst, args.form, args.every))


if __name__ == "__main__":
    main()
