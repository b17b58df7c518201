"""What the contraction probe reads, over seeds: the shares of a contracted grid's density and
occupied cells inside the box the cameras see, at several step counts of the probe's training.

    python benchmarks/probe_shares.py SCENE [--seeds 0,1,2] [--steps 400,800,1200,1600]
        [--seconds 60] [--device cuda]

Trains ``SCENE`` as :func:`ngp_warp.training.contraction_probe.probed_trainer` does before it
decides (``contraction_fit="seen"``, the schedule of a ``--seconds`` budget, the device's
sizes), once per seed, and prints one row per seed and step count: the two shares, their sum
(the probe tells an object where it reaches ``PROBE_SCORE``) and the training seconds. An object
before a distant backdrop keeps both inside the box; a scene with content around its cameras
spreads them beyond it.
"""

from __future__ import annotations

import argparse
import dataclasses
import gc

import torch

from ngp_warp.data.loading import load_scene
from ngp_warp.training.config import TrainConfig
from ngp_warp.training.contraction_probe import PROBE_SCORE, shares_inside
from ngp_warp.training.trainer import Trainer


def probe_shares(scene, seed: int, marks: list[int], seconds: float, device: str,
                 config: TrainConfig | None = None) -> list[dict]:
    """One probe's training of ``scene`` to ``max(marks)`` steps: a row per mark with ``step``,
    ``share`` (density), ``cells`` (occupied cells), ``score`` (their sum) and ``seconds``.
    ``config`` (left as it is; a copy's seed, budget and ``contraction_fit`` replaced) sets the sizes."""
    config = dataclasses.replace(config or TrainConfig(), seed=seed, seconds=seconds, steps=None, contraction_fit="seen")
    trainer = Trainer(scene, config, device=device)
    rows = []

    def read() -> bool:  # at each readout; True once the last mark is read
        if trainer.step_count in marks and all(r["step"] != trainer.step_count for r in rows):
            share, cells = shares_inside(trainer.grid)
            rows.append({"seed": seed, "step": trainer.step_count, "share": share, "cells": cells,
                         "score": share + cells, "seconds": trainer.train_seconds})
        return len(rows) == len(marks)

    trainer.train(show_progress=False, stop=(max(marks), None), until=read)
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scene")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--steps", default="400,800,1200,1600", help="step counts to read at (multiples of 10)")
    parser.add_argument("--seconds", type=float, default=60.0, help="the budget whose schedule the probe follows")
    parser.add_argument("--downscale", type=int, default=1)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = parser.parse_args(argv)
    marks = sorted(int(s) for s in args.steps.split(","))
    scene = load_scene(args.scene, downscale=args.downscale)
    print(f"| scene | seed | step | density inside | occupied cells inside | sum (object from {PROBE_SCORE}) | seconds |\n"
          "|---|---:|---:|---:|---:|---:|---:|")
    for seed in (int(s) for s in args.seeds.split(",")):
        for r in probe_shares(scene, seed, marks, args.seconds, args.device):
            print(f"| {args.scene} | {seed} | {r['step']} | {r['share']:.3f} | {r['cells']:.3f} | {r['score']:.2f} "
                  f"| {r['seconds']:.1f} |", flush=True)
        gc.collect()  # a trainer refers to itself: free its device memory before the next seed
        if torch.cuda.is_available():
            torch.cuda.empty_cache()


if __name__ == "__main__":
    main()
