"""``ngp-warp process`` on scenes with known poses: registered images, wall-clock time, mean
reprojection error, and the pose error after the best similarity alignment.

    python3 benchmarks/bench_process.py [--fox ../shared/data/fox] [--lego ../shared/data/lego_half]
                                        [--views 40] [--size 256] [--runs 1]

Rows: the demo scene in its textured room (``ngp_warp.data.scene.render_room_views``, known cameras)
and, when their folders exist, 40 of lego's training views composited on white (reference:
their transforms) and fox (its 50 photos; reference: fox's own transforms.json), each ``--runs``
times (features and matches differ from run to run). Columns: the mapper whose model was kept
and how many images contradict their own matches (``ngp_warp.data.fold_check``).
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from capture_scenes import composite, synthetic_views
from ngp_warp.data import scene as demo
from ngp_warp.data.process import ProcessConfig, pose_errors, process, require_pycolmap


def _demo_photos(folder: Path, n_views: int, size: int) -> dict[str, np.ndarray]:
    """Render the room views into ``folder``; {file name: [3, 4] float64 camera-to-world}."""
    c2w, _ = demo.demo_cameras(n_views, 1, seed=0)
    fx = 0.5 * size / math.tan(0.5 * demo.CAMERA_ANGLE_X)
    intrinsics = torch.tensor([[fx, fx, size / 2, size / 2]], dtype=torch.float32).expand(n_views, 4)
    rgb = demo.render_room_views(torch.from_numpy(c2w).float(), intrinsics.contiguous(), size, size)
    folder.mkdir(parents=True)
    for i, image in enumerate((rgb * 255 + 0.5).clamp(0, 255).to(torch.uint8).numpy()):
        iio.imwrite(folder / f"{i:03d}.png", image)
    return {f"{i:03d}.png": m for i, m in enumerate(c2w)}


def _fox_poses(fox: Path) -> dict[str, np.ndarray]:
    meta = json.loads((fox / "transforms.json").read_text())
    return {Path(f["file_path"]).name: np.array(f["transform_matrix"], dtype=np.float64) for f in meta["frames"]}


def _lego_photos(lego: Path, folder: Path, n_views: int) -> dict[str, np.ndarray]:
    """The first ``n_views`` training views of NeRF-synthetic ``lego``, composited on white,
    into ``folder``; {file name: [4, 4] float64 camera-to-world}."""
    folder.mkdir(parents=True)
    poses = {}
    for i, (image, c2w, _) in enumerate(synthetic_views(lego)[:n_views]):  # the train split comes first
        iio.imwrite(folder / f"{i:03d}.png", composite(iio.imread(image), np.ones(3)))
        poses[f"{i:03d}.png"] = c2w
    return poses


def _row(name: str, photos: Path, reference: dict[str, np.ndarray], work: Path, device: str) -> dict:
    start = time.perf_counter()
    report = process(photos, work / name, ProcessConfig(device=device, show_progress=False))
    seconds = time.perf_counter() - start
    meta = json.loads((work / name / "transforms.json").read_text())
    names = [Path(f["file_path"]).name for f in meta["frames"]]
    posed = np.array([f["transform_matrix"] for f in meta["frames"]])
    rotation, centre, spread = pose_errors(posed, np.stack([reference[n] for n in names]))
    return {"scene": name, "registered": f"{report.registered}/{report.total}", "seconds": seconds,
            "reproj_px": report.mean_reprojection_error, "rot_median_deg": float(np.median(rotation)),
            "rot_max_deg": rotation.max(), "centre_max_pct": 100 * centre.max() / spread, "stages": report.seconds,
            "mapper": report.mapper, "contradicted": len(report.contradicted)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--fox", default="../shared/data/fox", help="fox folder (images/, transforms.json)")
    parser.add_argument("--lego", default="../shared/data/lego_half", help="NeRF-synthetic lego folder")
    parser.add_argument("--views", type=int, default=40)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--runs", type=int, default=1, help="runs of each scene")
    parser.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"))
    args = parser.parse_args()
    pycolmap = require_pycolmap()
    pycolmap.logging.minloglevel = 2
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_process.") as tmp:
        work = Path(tmp)
        scenes = [(f"demo room {args.views}x{args.size}px", work / "demo_photos",
                   _demo_photos(work / "demo_photos", args.views, args.size))]
        lego, fox = Path(args.lego), Path(args.fox)
        if (lego / "transforms_train.json").is_file():
            scenes.append((f"lego {args.views} over white", work / "lego_photos",
                           _lego_photos(lego, work / "lego_photos", args.views)))
        if (fox / "transforms.json").is_file():
            scenes.append(("fox", fox / "images", _fox_poses(fox)))
        for name, photos, reference in scenes:
            for run in range(args.runs):
                rows.append(_row(name, photos, reference, work / f"run{run}", args.device))
    print(f"{'scene':<24} {'registered':>10} {'time s':>8} {'reproj px':>9} {'rot median°':>11} {'rot max°':>8} "
          f"{'centre max % spread':>19} {'mapper':>11} {'contradicted':>12}")
    for r in rows:
        print(f"{r['scene']:<24} {r['registered']:>10} {r['seconds']:8.1f} {r['reproj_px']:9.3f} "
              f"{r['rot_median_deg']:11.3f} {r['rot_max_deg']:8.3f} {r['centre_max_pct']:19.2f} {r['mapper']:>11} "
              f"{r['contradicted']:>12}")
    for r in rows:
        print(f"{r['scene']}: " + ", ".join(f"{k} {v:.1f} s" for k, v in r["stages"].items()))


if __name__ == "__main__":
    main()
