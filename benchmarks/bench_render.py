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
import time

import torch

from ngp_warp import OccupancyGrid, ray_marching
from ngp_warp.render import composite_packed

AABB = torch.tensor([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0])
RADIUS = 0.6


def scene_grid(kind: str, device: str) -> OccupancyGrid:
    grid = OccupancyGrid(AABB, resolution=128).to(device)
    if kind == "sphere":
        density = lambda p: (p.norm(dim=-1) < RADIUS).float()  # noqa: E731
    else:
        density = lambda p: ((p.norm(dim=-1) - RADIUS).abs() < 0.02).float()  # noqa: E731
    grid.update(0, density)
    return grid


def make_rays(n: int, device: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays from radius 3 aimed inside the sphere's silhouette (every ray hits it)."""
    g = torch.Generator().manual_seed(0)
    o = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1) * 3.0
    aim = (torch.rand(n, 3, generator=g) * 2 - 1) * RADIUS * 0.5
    d = torch.nn.functional.normalize(aim - o, dim=-1)
    return o.to(device), d.to(device)


def timed(fn, iters: int, device: str) -> float:
    """Seconds per call of ``fn`` (after two warm-up calls)."""
    for _ in range(2):
        fn()
    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    sync()
    t0 = time.perf_counter()
    for _ in range(iters):
        fn()
    sync()
    return (time.perf_counter() - t0) / iters


def bench_scene(kind: str, device: str, target_samples: int, iters: int) -> list[dict]:
    grid = scene_grid(kind, device)
    probe_o, probe_d = make_rays(1024, device)
    per_ray = max(ray_marching(probe_o, probe_d, grid).n_samples / 1024, 1.0)
    n_rays = max(1, round(target_samples / per_ray))
    rays_o, rays_d = make_rays(n_rays, device)
    samples = ray_marching(rays_o, rays_d, grid)
    s = samples.n_samples
    sigmas = (torch.rand(s, device=device) * 2).requires_grad_(True)
    rgbs = torch.rand(s, 3, device=device).requires_grad_(True)
    g_rgb = torch.rand(n_rays, 3, device=device)

    def march():
        return ray_marching(rays_o, rays_d, grid)

    def forward():
        return composite_packed(sigmas, rgbs, samples.t_starts, samples.t_ends, samples.ray_offsets, 1e-4)

    out = forward()

    def backward():
        torch.autograd.grad(out[0], (sigmas, rgbs), g_rgb, retain_graph=True)

    def total():
        m = march()
        rgb = composite_packed(sigmas, rgbs, m.t_starts, m.t_ends, m.ray_offsets, 1e-4)[0]
        torch.autograd.grad(rgb, (sigmas, rgbs), g_rgb)

    rows = []
    for op, fn in (("march", march), ("composite fwd", forward), ("composite bwd", backward),
                   ("march+fwd+bwd", total)):
        sec = timed(fn, iters, device)
        rows.append({"scene": kind, "op": op, "device": device, "rays": n_rays, "samples": s,
                     "ms": sec * 1e3, "rays_per_s": n_rays / sec, "samples_per_s": s / sec})
    return rows


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
    head = f"{'scene':<7} {'op':<14} {'rays':>7} {'samples':>8} {'ms':>9} {'Mrays/s':>9} {'Msamples/s':>11}"
    print(f"device: {args.device}" + (f" ({torch.cuda.get_device_name()})" if args.device.startswith("cuda") else ""))
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r['scene']:<7} {r['op']:<14} {r['rays']:>7} {r['samples']:>8} {r['ms']:>9.3f} "
              f"{r['rays_per_s'] / 1e6:>9.2f} {r['samples_per_s'] / 1e6:>11.2f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"device": args.device, "rows": rows}, f, indent=2)
    assert all(math.isfinite(r["ms"]) for r in rows)


if __name__ == "__main__":
    main()
