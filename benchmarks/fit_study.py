"""How much of a capture's held-out PSNR is the appearance fit: one trained run's test views
scored on their right halves with codes fitted on the left half in several ways.

    python benchmarks/fit_study.py RUN_DIR [--fit ITERATIONS:LR:SEED[:pose] ...]

Each ``--fit`` is Adam's iterations, learning rate and pixel seed for
:func:`ngp_warp.training.appearance_fit.fit_appearance_code` (default: the evaluation's own, then its
pixels redrawn, then longer and slower fits); ``:pose`` fits the view's pose as well
(:func:`ngp_warp.training.appearance_fit.fit_appearance_and_pose`: how much of the error is the view's
registration). A fit whose PSNR moves with its seed is noisy; one
that gains with more iterations is not converged. Prints a table: per view and the mean.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from ngp_warp.training.appearance_fit import FIT_ITERATIONS, FIT_LR, fit_appearance_and_pose, fit_appearance_code, right_half
from ngp_warp.training.checkpoint import CheckpointError, load_trainer
from ngp_warp.outputs.evaluate import composite_on
from ngp_warp.outputs.metrics import psnr

DEFAULT_FITS = [f"{FIT_ITERATIONS}:{FIT_LR}:0", f"{FIT_ITERATIONS}:{FIT_LR}:1", f"{FIT_ITERATIONS}:{FIT_LR}:2",
                f"{3 * FIT_ITERATIONS}:{FIT_LR}:0", f"{3 * FIT_ITERATIONS}:{FIT_LR / 3}:0"]


def trainer_or_usage_error(ap: argparse.ArgumentParser, run: str, device: str, need_codes: bool = False):
    """The trainer of the run folder ``run``'s checkpoint, or argparse's usage error with the
    one-line reason (a missing or foreign checkpoint; a field without appearance codes when
    ``need_codes``)."""
    try:
        trainer, _ = load_trainer(Path(run) / "checkpoint.pt", device=device)
    except CheckpointError as e:
        ap.error(str(e))
    if need_codes and trainer.field.appearance is None:
        ap.error("this run's field has no appearance codes")
    return trainer


def held_out_views(trainer):
    """Yield ``(name, camera, ground truth)`` for every test view of ``trainer``'s scene: the
    camera as :meth:`Split.camera` gives it, the image [H, W, 3] float32 composited on white on
    the trainer's device (as the evaluation scores it)."""
    split, white = trainer.scene.test, torch.ones(3, device=trainer.device)
    for i, name in enumerate(split.names):
        yield name, split.camera(i), composite_on(split.images[i].to(trainer.device), white)


def _parse_fit(spec: str) -> tuple[int, float, int, bool]:
    parts = spec.split(":")
    if len(parts) not in (3, 4) or (len(parts) == 4 and parts[3] != "pose"):
        raise ValueError(spec)
    return int(parts[0]), float(parts[1]), int(parts[2]), len(parts) == 4


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--fit", nargs="+", default=DEFAULT_FITS, metavar="ITERATIONS:LR:SEED[:pose]")
    args = ap.parse_args()
    try:
        fits = [_parse_fit(f) for f in args.fit]
    except ValueError:
        ap.error(f"--fit takes ITERATIONS:LR:SEED[:pose], got {' '.join(args.fit)}")
    trainer = trainer_or_usage_error(ap, args.run, args.device, need_codes=True)
    background = trainer.view_background
    rows = []
    for name, camera, gt in held_out_views(trainer):
        scores = []
        for iterations, lr, seed, pose in fits:
            fit = dict(image=gt, background=background, iterations=iterations, lr=lr, seed=seed)
            if pose:
                code, c2w = fit_appearance_and_pose(trainer, **camera, **fit)
            else:
                code, c2w = fit_appearance_code(trainer, **camera, **fit), camera["c2w"]
            out = trainer.render_image(**{**camera, "c2w": c2w}, background=background, appearance_code=code)
            scores.append(psnr(right_half(out["rgb"]), right_half(gt)))
        rows.append((name, scores))
        print(name, " ".join(f"{s:.2f}" for s in scores), flush=True)
    print("\n| view | " + " | ".join(f"{i} it, lr {lr:g}, seed {s}{', pose' if p else ''}" for i, lr, s, p in fits)
          + " |")
    print("| --- |" + " ---: |" * len(fits))
    for name, scores in rows:
        print(f"| {Path(name).stem} | " + " | ".join(f"{s:.2f}" for s in scores) + " |")
    means = np.mean([scores for _, scores in rows], axis=0)
    print("| **mean** | " + " | ".join(f"**{m:.2f}**" for m in means) + " |")


if __name__ == "__main__":
    main()
