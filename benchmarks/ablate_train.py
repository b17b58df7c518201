"""Compare training settings on one scene: test PSNR at a few checkpoints for each variant.

    python benchmarks/ablate_train.py ../shared/data/lego_half --checkpoints 15,60 --test-every 8 \\
        --variant base: --variant ema0:weight_average=0 --variant fine1k:field.finest_resolution=1024

A variant is ``NAME:KEY=VALUE,KEY=VALUE`` with keys as in ``bench_train.py --set``; every variant
starts from the same defaults and seed. The scene is loaded and the kernels compiled once.
"""

from __future__ import annotations

import argparse
import gc
import json
import time
from pathlib import Path

import torch

from bench_train import scene_or_usage_error, train_and_evaluate, warm_up
from ngp_warp.training.config import TrainConfig, apply_overrides
from ngp_warp.training.trainer import Trainer


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--checkpoints", default="15,60")
    ap.add_argument("--test-every", type=int, default=8)
    ap.add_argument("--variant", action="append", required=True, metavar="NAME:KEY=VALUE,...")
    ap.add_argument("--spp", type=int, default=1, help="also score renders at this many points per pixel")
    ap.add_argument("--json", help="write all rows here")
    args = ap.parse_args()

    marks = [float(s) for s in args.checkpoints.split(",")]
    scene = scene_or_usage_error(ap, args.scene)
    variants = []
    for spec in args.variant:
        name, _, settings = spec.partition(":")
        try:
            cfg = apply_overrides(TrainConfig(seconds=marks[-1]), [s for s in settings.split(",") if s])
        except ValueError as e:
            ap.error(f"variant {name}: {e}")
        variants.append((name, cfg))
    results = {}
    for i, (name, cfg) in enumerate(variants):
        if i == 0 or cfg.field != variants[i - 1][1].field:
            start = time.perf_counter()
            warm_up(scene, cfg, args.device)
            print(f"warm-up (kernel compilation) {time.perf_counter() - start:.1f} s", flush=True)
        print(f"== {name}", flush=True)
        results[name] = train_and_evaluate(Trainer(scene, cfg, device=args.device), marks, args.test_every, args.spp)
        if args.json:
            Path(args.json).write_text(json.dumps(results, indent=2))
        gc.collect()  # a captured graph holds a reference cycle: free the last variant's memory
        if torch.cuda.is_available():
            torch.cuda.empty_cache()

    spp = [f"{args.spp} spp @{m:.0f} s" for m in marks] if args.spp > 1 else []
    print(f"\n| variant | " + " | ".join([f"PSNR @{m:.0f} s" for m in marks] + spp) + " | ms/step (last) |")
    print("| --- |" + " ---: |" * (len(marks) + len(spp) + 1))
    for name, rows in results.items():
        cells = [f"{r['psnr']:.2f}" for r in rows] + ([f"{r['psnr_spp']:.2f}" for r in rows] if spp else [])
        print(f"| {name} | " + " | ".join(cells) + f" | {rows[-1]['ms_per_step']:.2f} |")


if __name__ == "__main__":
    main()
