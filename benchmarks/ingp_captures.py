"""Official instant-ngp on the capture benchmark's scenes: the same images, the same held-out
frames, the conventions its users follow.

Two steps, the first anywhere, the second on the GPU machine beside instant-ngp's build
(``../shared/ingp/``: ``build.sh`` and its ``run_fox.py``, which trains on a ``transforms.json``
without a test split, holds out every 8th frame sorted by name as ``ngp-warp train`` does, and
scores the held-out views on the whole image and its right half):

    python benchmarks/ingp_captures.py write --lego ../shared/data/lego_half --out DIR
        [--scenes lego-colmap,demo-colmap,...]
    for s in DIR/*-a*/; do python run_fox.py --scene $s --seconds 60 --out RESULTS/$(basename $s).json ...; done
    python benchmarks/ingp_captures.py table --out RESULTS

``write`` writes each capture scene of ``bench_captures.py`` (``DIR/captures/NAME``) and beside it
what an instant-ngp user trains on (``DIR/NAME-aSCALE``, images copied):

* a COLMAP model becomes a ``transforms.json`` as instant-ngp's ``colmap2nerf.py`` writes one:
  camera up turned to +z, the point the cameras look at moved to the origin, the mean camera
  distance scaled to 4, ``aabb_scale`` 32 (its default);
* an instant-ngp form (``lego-ngp``, ``demo-ngp``) is kept as written: the NeRF-synthetic poses
  and no ``aabb_scale`` (1, the box that holds the object);
* ``--aabb-scale N`` adds the COLMAP scenes once more with that box.

``table`` prints one row per run (``RESULTS/NAME-aSCALE.json``): PSNR on black (instant-ngp's
renders of opaque photos) and on white, the right half, SSIM, steps and ms per step.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_captures import scene_folder  # noqa: E402

COLMAP2NERF_AABB_SCALE = 32  # colmap2nerf.py's default box
COLMAP2NERF_CAMERA_DISTANCE = 4.0  # colmap2nerf.py scales the mean camera distance to this
COLMAP2NERF_WORLD = np.diag([1.0, 1.0, -1.0, 1.0])[[1, 0, 2, 3]]  # its world: x and y swapped, z flipped
DEFAULT_SCENES = ("lego-colmap", "lego-ngp", "lego-colmap-sky", "demo-colmap", "demo-ngp", "demo-colmap-sky",
                  "unbounded-colmap", "room-colmap")


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[3, 3] float64 rotation taking the unit vector ``a`` [3] to the unit vector ``b`` [3] (for
    opposite vectors, the half turn about an axis normal to ``a``)."""
    v, c = np.cross(a, b), float(a @ b)
    if np.linalg.norm(v) < 1e-12:
        if c > 0:
            return np.eye(3)
        normal = np.cross(a, np.eye(3)[np.argmin(np.abs(a))])
        normal /= np.linalg.norm(normal)
        return 2 * np.outer(normal, normal) - np.eye(3)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k * ((1 - c) / (v @ v))


def looked_at_point(c2w: np.ndarray) -> np.ndarray:
    """[3] float64: the weighted mean over camera pairs of the points where their optical axes
    pass closest (colmap2nerf's centre of attention); ``c2w`` [N, 4, 4] OpenGL camera-to-world.
    Parallel axes weigh nothing; a closest point behind a camera is moved to that camera's centre."""
    total, weight = np.zeros(3), 0.0
    for a in c2w:
        for b in c2w:
            oa, ob = a[:3, 3], b[:3, 3]
            da, db = a[:3, 2] / np.linalg.norm(a[:3, 2]), b[:3, 2] / np.linalg.norm(b[:3, 2])
            c = np.cross(da, db)
            w = float(c @ c)
            if w <= 1e-5:
                continue
            t = ob - oa
            ta = min(np.linalg.det([t, db, c]) / (w + 1e-10), 0.0)
            tb = min(np.linalg.det([t, da, c]) / (w + 1e-10), 0.0)
            total += (oa + ta * da + ob + tb * db) * 0.5 * w
            weight += w
    return total / weight if weight > 0 else np.zeros(3)


def colmap2nerf_poses(c2w: np.ndarray) -> np.ndarray:
    """[N, 4, 4] float64: the OpenGL camera-to-world ``c2w`` [N, 4, 4] of a COLMAP model (in its
    world) placed as colmap2nerf places them: the world's x and y swapped and z flipped, the mean
    camera up turned to +z, the centre of attention moved to the origin, the mean camera distance
    scaled to 4."""
    poses = COLMAP2NERF_WORLD @ c2w
    up = poses[:, :3, 1].sum(0)
    turn = np.eye(4)
    turn[:3, :3] = rotation_between(up / np.linalg.norm(up), np.array([0.0, 0.0, 1.0]))
    poses = turn @ poses
    poses[:, :3, 3] -= looked_at_point(poses)
    poses[:, :3, 3] *= COLMAP2NERF_CAMERA_DISTANCE / np.linalg.norm(poses[:, :3, 3], axis=1).mean()
    return poses


def write_ingp_form(capture: Path, dst: Path, aabb_scale: int | None) -> Path:
    """Write ``dst`` (``transforms.json`` + ``images/``) from the capture folder ``capture``
    (a COLMAP text model or an instant-ngp form); ``aabb_scale`` None keeps the form's own."""
    from ngp_warp.data.colmap import camera_keys, camera_to_world, read_colmap_model

    shutil.copytree(capture / "images", dst / "images")
    if (capture / "transforms.json").is_file():
        meta = json.loads((capture / "transforms.json").read_text())
    else:
        model = read_colmap_model(capture / "sparse" / "0")
        if len(model.cameras) != 1:
            raise SystemExit(f"{capture}: {len(model.cameras)} cameras; the capture scenes have one")
        poses = colmap2nerf_poses(np.stack([camera_to_world(im) for im in model.images]))
        meta = dict(camera_keys(next(iter(model.cameras.values()))))
        meta["frames"] = [{"file_path": f"images/{im.name}", "transform_matrix": p.tolist()}
                          for im, p in zip(model.images, poses)]
        meta["aabb_scale"] = COLMAP2NERF_AABB_SCALE
    if aabb_scale is not None:
        meta["aabb_scale"] = aabb_scale
    (dst / "transforms.json").write_text(json.dumps(meta, indent=1))
    return dst


def write(args) -> None:
    for name in args.scenes.split(","):
        capture = scene_folder(name, args.out / "captures", args)
        boxes = [None] + ([args.aabb_scale] if args.aabb_scale and "colmap" in name else [])
        for box in boxes:
            meta_box = box if box is not None else (1 if name.endswith("-ngp") else COLMAP2NERF_AABB_SCALE)
            dst = args.out / f"{name}-a{meta_box}"
            if not dst.exists():
                write_ingp_form(capture, dst, box)
            print(dst)


def table(args) -> None:
    lines = ["| scene | aabb_scale | PSNR whole (black) | whole (white) | right half (black) | SSIM | steps | ms/step |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for path in sorted(args.out.glob("*-a*.json")):
        name, box = path.stem.rsplit("-a", 1)
        result = json.loads(path.read_text())
        if not result.get("checkpoints"):
            lines.append(f"| {name} | {box} | failed: {result.get('error', 'no checkpoint')} | | | | | |")
            continue
        last = result["checkpoints"][-1]
        ev = last["eval"]
        lines.append(f"| {name} | {box} | {ev['psnr']:.2f} | {ev['white_bg']['psnr']:.2f} | {ev['psnr_right_half']:.2f} "
                     f"| {ev['ssim']:.4f} | {last['steps']} | {last['ms_per_step']:.2f} |")
    print("\n".join(lines))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("step", choices=("write", "table"))
    parser.add_argument("--out", type=Path, required=True, help="write: the folder of instant-ngp forms; table: the folder of run_fox.py's results")
    parser.add_argument("--scenes", default=",".join(DEFAULT_SCENES))
    parser.add_argument("--lego", type=Path, help="lego_half (NeRF-synthetic folder)")
    parser.add_argument("--aabb-scale", type=int, help="also write each COLMAP scene with this box")
    args = parser.parse_args()
    args.fox = None  # bench_captures.scene_folder reads it; fox ships as instant-ngp's own form
    if args.step == "write":
        write(args)
    else:
        table(args)


if __name__ == "__main__":
    main()
