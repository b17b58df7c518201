"""Benchmark the render op: ray marching, compositing forward and backward, and all three.

Two scenes of about 2^18 samples per batch in the box [-1, 1]^3 with a 128³ grid and the default
step (box diagonal / 1024): ``sphere``, a solid occupied sphere (long rays, few of them), and
``shell``, a thin spherical shell like a trained grid around a surface (~30 samples per ray).
Times are wall-clock per call, averaged over ``--iters`` calls after warm-up, with the device
synchronised, so they include Python and launch overheads.

    python benchmarks/bench_render.py --device cuda [--json results.json]
"""

from __future__ import annotations

import argparse
import json
import math

import torch

from ngp_warp.outputs.bench import bench_scene


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--samples", type=int, default=1 << 18, help="target samples per batch")
    parser.add_argument("--iters", type=int, default=None, help="timed calls per op (default 200 GPU, 5 CPU)")
    parser.add_argument("--json", metavar="PATH", help="also write the rows as JSON")
    args = parser.parse_args(argv)
    iters = args.iters or (200 if args.device.startswith("cuda") else 5)
    torch.manual_seed(0)
    rows = [r for kind in ("sphere", "shell") for r in bench_scene(kind, args.device, args.samples, iters)]
    head = f"{'scene':<7} {'op':<16} {'rays':>7} {'samples':>8} {'ms':>9} {'Mrays/s':>9} {'Msamples/s':>11}"
    print(f"device: {args.device}" + (f" ({torch.cuda.get_device_name()})" if args.device.startswith("cuda") else ""))
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r['scene']:<7} {r['op']:<16} {r['rays']:>7} {r['samples']:>8} {r['ms']:>9.3f} "
              f"{r['rays_per_s'] / 1e6:>9.2f} {r['samples_per_s'] / 1e6:>11.2f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"device": args.device, "rows": rows}, f, indent=2)
    assert all(math.isfinite(r["ms"]) for r in rows)


if __name__ == "__main__":
    main()
