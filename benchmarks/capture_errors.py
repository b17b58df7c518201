"""Where a trained capture's error is: training against held-out views, by distance from the
image centre, and by the ground truth's texture.

    python benchmarks/capture_errors.py RUN_DIR [--train-every 6] [--pictures DIR]

Every view is rendered with the code fitted on its left half (as ``ngp-warp eval`` does for
scenes with appearance codes) and scored on its right half. A training view that scores no
better than the held-out ones means the field cannot fit even the pixels it trained on:
inconsistent cameras (poses, lens) or too small a field, not over-fitting. The error by radius
(four rings of the normalised distance from the principal point) grows outwards when the lens
model is wrong; the error by texture (quartiles of the ground truth's gradient magnitude)
gathers at edges when views disagree by a shift (poses) or the field blurs. ``--pictures``
writes render | ground truth | 4× error for the worst held-out view.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from fit_study import trainer_or_usage_error
from ngp_warp.training.appearance_fit import fit_appearance_code, right_half
from ngp_warp.outputs.evaluate import composite_on, to_uint8

RINGS = 4


def _db(mse: float) -> float:
    return float(-10.0 * np.log10(max(mse, 1e-12)))


def view_errors(trainer, split, i: int, background: float) -> tuple[dict, torch.Tensor, torch.Tensor]:
    """One view's right-half scores: ``psnr``, ``rings`` [RINGS] and ``texture`` [4] PSNRs; and
    the render and ground truth ([H, W, 3] float32)."""
    camera = split.camera(i)
    white = torch.ones(3, device=trainer.device)
    gt = composite_on(split.images[i].to(trainer.device), white)
    code = fit_appearance_code(trainer, **camera, image=gt, background=background)
    rgb = trainer.render_image(**camera, background=background, appearance_code=code)["rgb"]
    sq = right_half((rgb - gt).square().mean(-1, keepdim=True))[..., 0]
    h, w = gt.shape[:2]
    fx, fy, cx, cy = camera["intrinsics"].tolist()
    ys, xs = torch.meshgrid(torch.arange(h, device=gt.device), torch.arange(w, device=gt.device), indexing="ij")
    radius = torch.sqrt(((xs + 0.5 - cx) / (w / 2)) ** 2 + ((ys + 0.5 - cy) / (h / 2)) ** 2) / np.sqrt(2)
    radius = right_half(radius[..., None])[..., 0]
    grey = gt.mean(-1)
    grad = torch.zeros_like(grey)
    grad[1:-1, 1:-1] = (grey[1:-1, 2:] - grey[1:-1, :-2]).abs() + (grey[2:, 1:-1] - grey[:-2, 1:-1]).abs()
    grad = right_half(grad[..., None])[..., 0]
    ring = (radius * RINGS).long().clamp(0, RINGS - 1)
    rings = [_db(float(sq[ring == k].mean())) if (ring == k).any() else float("nan") for k in range(RINGS)]
    order = torch.argsort(grad.flatten())
    texture = [_db(float(part.mean())) for part in sq.flatten()[order].chunk(4)]
    return {"psnr": _db(float(sq.mean())), "rings": rings, "texture": texture}, rgb, gt


def summarise(label: str, rows: list[dict]) -> None:
    rings = np.nanmean([r["rings"] for r in rows], axis=0)
    texture = np.mean([r["texture"] for r in rows], axis=0)
    print(f"| {label} ({len(rows)}) | {np.mean([r['psnr'] for r in rows]):.2f} | "
          + " | ".join(f"{v:.2f}" for v in rings) + " | " + " | ".join(f"{v:.2f}" for v in texture) + " |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--train-every", type=int, default=6)
    ap.add_argument("--pictures", type=Path, default=None)
    args = ap.parse_args()
    if args.train_every < 1:
        ap.error(f"--train-every must be ≥ 1, got {args.train_every}")
    trainer = trainer_or_usage_error(ap, args.run, args.device, need_codes=True)
    background = trainer.view_background
    scene = trainer.scene
    held_out = [view_errors(trainer, scene.test, i, background) for i in range(len(scene.test.names))]
    trained = [view_errors(trainer, scene.train, i, background)[0]
               for i in range(0, len(scene.train.names), args.train_every)]
    print("| views | PSNR | " + " | ".join(f"ring {k + 1}" for k in range(RINGS))
          + " | flattest | texture 2 | texture 3 | edges |")
    print("| --- |" + " ---: |" * (1 + RINGS + 4))
    summarise("held out", [r for r, _, _ in held_out])
    summarise("training", trained)
    if args.pictures is not None:
        worst = min(range(len(held_out)), key=lambda k: held_out[k][0]["psnr"])
        _, rgb, gt = held_out[worst]
        error = ((rgb - gt).abs() * 4.0).clamp(0, 1)
        args.pictures.mkdir(parents=True, exist_ok=True)
        name = Path(scene.test.names[worst]).stem
        iio.imwrite(args.pictures / f"{name}_render_gt_error.jpg",
                    to_uint8(torch.cat([rgb, gt, error], dim=1)), quality=90)
        print(f"pictures: {args.pictures / name}_render_gt_error.jpg ({held_out[worst][0]['psnr']:.2f} dB)")


if __name__ == "__main__":
    main()
