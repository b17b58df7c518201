"""Where a contracted field puts its density while it trains: the share of the occupancy grid's
density (and of its occupied cells) inside the contraction's inner box, after each of several
step counts.

    python benchmarks/inner_density.py SCENE [--downscale N] [--fit seen] [--steps 200,400,800]
        [--device cpu] [--seed 0]

Trains ``SCENE`` contracted (``contraction=l2``) with the inner box ``--fit`` gives
(:func:`ngp_warp.training.scene_defaults.contraction_box`; the CLI's sizes for the device) and
prints one row per step count. With the box the cameras see (``seen``), an object before a
backdrop at infinity keeps its density inside the box (the backdrop is the field's environment),
while a scene with content around its cameras puts a share of it outside: the question is how
early the two tell apart.
"""

from __future__ import annotations

import argparse
import time

import torch

from ngp_warp.data.loading import load_scene
from ngp_warp.training.config import TrainConfig, cpu_sizes
from ngp_warp.training.contraction_probe import shares_inside
from ngp_warp.training.scene_defaults import CONTRACTION_FITS
from ngp_warp.training.trainer import Trainer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scene")
    parser.add_argument("--downscale", type=int, default=1)
    parser.add_argument("--fit", choices=CONTRACTION_FITS, default="seen")
    parser.add_argument("--steps", default="200,400,800,1200", help="comma-separated step counts to report at")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    marks = sorted(int(s) for s in args.steps.split(","))
    torch.manual_seed(args.seed)
    scene = load_scene(args.scene, downscale=args.downscale)
    config = TrainConfig(steps=marks[-1], seed=args.seed, contraction="l2", contraction_fit=args.fit)
    trainer = Trainer(scene, cpu_sizes(config) if args.device == "cpu" else config, device=args.device)
    print("| scene | fit | step | density inside | occupied cells inside | seconds |\n|---|---|---:|---:|---:|---:|")
    start = time.perf_counter()
    for step in range(1, marks[-1] + 1):
        trainer.step(step / marks[-1])
        if step in marks:
            trainer.flush()
            density, cells = shares_inside(trainer.grid)
            seconds = time.perf_counter() - start
            print(f"| {args.scene} | {args.fit} | {step} | {density:.3f} | {cells:.3f} | {seconds:.0f} |", flush=True)


if __name__ == "__main__":
    main()
