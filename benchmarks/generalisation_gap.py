"""Training-view versus test-view PSNR during one run: is the model overfitting?

    python benchmarks/generalisation_gap.py ../shared/data/lego_half [--checkpoints 30,120] [--set KEY=VALUE]

Trains with the defaults (plus ``--set`` overrides as in ``bench_train.py``; the
learning-rate schedule runs over ``seconds``, 300 by default) and at each checkpoint renders every
8th test view and every 4th training view the same way (white background), plus the test views
averaged over 4 renders with jittered sample offsets ("4 spp").
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from bench_train import scene_or_usage_error, warm_up
from ngp_warp.training.config import TrainConfig, apply_overrides
from ngp_warp.data.loading import Split
from ngp_warp.outputs.evaluate import iter_test_renders
from ngp_warp.outputs.metrics import psnr
from ngp_warp.training.trainer import Trainer


def mean_psnr(trainer: Trainer, split: Split, every: int, spp: int = 1) -> float:
    return float(np.mean([psnr(out["rgb"], gt) for _, out, gt in iter_test_renders(trainer, every, split, spp)]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--checkpoints", default="30,120")
    ap.add_argument("--downscale", type=int, default=1)
    args = ap.parse_args()

    scene = scene_or_usage_error(ap, args.scene, args.downscale)
    try:
        cfg = apply_overrides(TrainConfig(seconds=300.0), args.set)
    except ValueError as e:
        ap.error(str(e))
    warm_up(scene, cfg, args.device)
    trainer = Trainer(scene, cfg, device=args.device)
    print("| train s | steps | test PSNR | test, 4 spp | training-view PSNR |")
    print("| ---: | ---: | ---: | ---: | ---: |")
    for mark in (float(s) for s in args.checkpoints.split(",")):
        while trainer.train_seconds < mark:
            trainer.step(progress=trainer.train_seconds / cfg.seconds)
        start = time.perf_counter()
        row = (mean_psnr(trainer, scene.test, 8), mean_psnr(trainer, scene.test, 8, spp=4),
               mean_psnr(trainer, scene.train, 4))
        print(f"| {mark:.0f} | {trainer.step_count} | " + " | ".join(f"{v:.2f}" for v in row) +
              f" |   ({time.perf_counter() - start:.0f} s to evaluate)", flush=True)


if __name__ == "__main__":
    main()
