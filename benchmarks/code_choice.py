"""Which appearance code suits a held-out view: one trained run's test views rendered with
several codes and scored on the whole image and on each half.

    python benchmarks/code_choice.py RUN_DIR [--scene SCENE_DIR]

Codes: the nearest training camera's (what metrics.json's ``psnr_nearest_code`` uses), the mean
of the two nearest, the three nearest weighted by inverse distance, the mean of all training
codes, and the code fitted on the view's own left half
(:func:`ngp_warp.training.appearance_fit.fit_appearance_code`). If the right half with the
nearest code scores what it scores with the fitted code, the held-out views' code is not what
limits the whole image; the field is. Prints a table: per view and the mean (PSNR in dB).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from ngp_warp.outputs.evaluate import composite_on
from ngp_warp.outputs.metrics import psnr
from ngp_warp.training.appearance_fit import fit_appearance_code, right_half
from ngp_warp.training.checkpoint import CheckpointError, load_trainer

CHOICES = ("nearest", "two nearest", "three nearest, 1/d", "mean", "fitted on the left half")


def candidate_codes(codes: torch.Tensor, centres: torch.Tensor, centre: torch.Tensor) -> list[torch.Tensor]:
    """The codes of :data:`CHOICES` but the fitted one, each [A] float32, for a view whose camera
    centre is ``centre`` ([3]); ``codes`` [N, A] and ``centres`` [N, 3] are the training images'."""
    distance = (centres - centre).norm(dim=-1)
    order = distance.argsort()
    inverse = 1.0 / distance[order[:3]].clamp_min(1e-9)
    return [codes[order[0]], codes[order[:2]].mean(0), (codes[order[:3]] * (inverse / inverse.sum())[:, None]).sum(0),
            codes.mean(0)]


def view_scores(rgb: torch.Tensor, gt: torch.Tensor) -> tuple[float, float, float]:
    """PSNR of ``rgb`` against ``gt`` ([H, W, 3] float32 each): whole, left half, right half."""
    half = gt.shape[1] // 2
    return psnr(rgb, gt), psnr(rgb[:, :half], gt[:, :half]), psnr(right_half(rgb), right_half(gt))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run", type=Path, help="a finished run's folder (its checkpoint.pt)")
    parser.add_argument("--scene", type=Path, help="the scene folder, where it moved since training")
    args = parser.parse_args()
    try:
        trainer, _ = load_trainer(args.run / "checkpoint.pt", scene_path=args.scene)
    except CheckpointError as e:
        raise SystemExit(f"code_choice: {e}") from None
    if trainer.field.appearance is None:
        raise SystemExit("code_choice: this run trained no appearance codes")
    codes = trainer.field.appearance.weight.detach()
    centres = trainer.train_split.c2w[:, :, 3].to(codes.device)
    split, white = trainer.scene.test, torch.ones(3, device=trainer.device)
    background = trainer.view_background
    rows = []
    for i, name in enumerate(split.names):
        camera = split.camera(i)
        gt = composite_on(split.images[i].to(trainer.device), white)
        choices = candidate_codes(codes, centres, camera["c2w"][:3, 3].to(centres))
        choices.append(fit_appearance_code(trainer, **camera, image=gt, background=background))
        scores = [view_scores(trainer.render_image(**camera, background=background, appearance_code=code)["rgb"], gt)
                  for code in choices]
        rows.append(scores)
        print(Path(name).name, "  ".join(f"{c}: {w:.2f}/{l:.2f}/{r:.2f}" for c, (w, l, r) in zip(CHOICES, scores)),
              flush=True)
    mean = np.mean(np.array(rows), axis=0)
    print("\n| code | whole | left half | right half |\n|---|---:|---:|---:|")
    for choice, (whole, left, right) in zip(CHOICES, mean):
        print(f"| {choice} | {whole:.2f} | {left:.2f} | {right:.2f} |")


if __name__ == "__main__":
    main()
