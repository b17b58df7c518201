"""Where the render op's time goes: device time per kernel against wall-clock per call.

    python benchmarks/profile_render_op.py [--device cuda] [--iters 50]

For both scenes of ``bench_render.py`` (sphere: few long rays; shell: ~30 samples per ray) and each
op (march; composite forward; backward; all three), prints the wall-clock per call (calls back to
back, device synchronised at the end, as ``bench_render`` times them), the device time per call
summed over its kernels (torch.profiler, CUPTI: Warp's kernels included) and the three kernels
that take the most of it. Wall minus device is time the GPU waits for the host or a sync.
"""

from __future__ import annotations

import argparse
import collections

import torch
from torch.profiler import ProfilerActivity, profile

from ngp_warp.outputs.bench import make_rays, scene_grid, timed
from ngp_warp.ops.raymarch import ray_marching
from ngp_warp.ops.render import composite_packed


def scene_ops(kind: str, device: str, target_samples: int) -> dict:
    """The four calls of ``bench_render`` for scene ``kind`` (see :func:`ngp_warp.outputs.bench.bench_scene`)."""
    grid = scene_grid(kind, device)
    probe_o, probe_d = make_rays(1024, device)
    per_ray = max(ray_marching(probe_o, probe_d, grid, validate=False).n_samples / 1024, 1.0)
    rays_o, rays_d = make_rays(max(1, round(target_samples / per_ray)), device)
    samples = ray_marching(rays_o, rays_d, grid, validate=False)
    sigmas = (torch.rand(samples.n_samples, device=device) * 2).requires_grad_(True)
    rgbs = torch.rand(samples.n_samples, 3, device=device).requires_grad_(True)
    g_rgb = torch.rand(rays_o.shape[0], 3, device=device)
    out = composite_packed(sigmas, rgbs, samples.t_starts, samples.t_ends, samples.ray_offsets, 1e-4)

    def total():
        m = ray_marching(rays_o, rays_d, grid, validate=False)
        rgb = composite_packed(sigmas, rgbs, m.t_starts, m.t_ends, m.ray_offsets, 1e-4)[0]
        torch.autograd.grad(rgb, (sigmas, rgbs), g_rgb)

    capacity = samples.n_samples + samples.n_samples // 8
    sigmas_c = torch.cat([sigmas.detach(), sigmas.detach()[: capacity - samples.n_samples]]).requires_grad_(True)
    rgbs_c = torch.cat([rgbs.detach(), rgbs.detach()[: capacity - samples.n_samples]]).requires_grad_(True)

    def total_no_sync():
        m = ray_marching(rays_o, rays_d, grid, validate=False, capacity=capacity)
        rgb = composite_packed(sigmas_c, rgbs_c, m.t_starts, m.t_ends, m.ray_offsets, 1e-4)[0]
        torch.autograd.grad(rgb, (sigmas_c, rgbs_c), g_rgb)

    return {
        "march": lambda: ray_marching(rays_o, rays_d, grid, validate=False),
        "march, capacity": lambda: ray_marching(rays_o, rays_d, grid, validate=False, capacity=capacity),
        "composite fwd": lambda: composite_packed(sigmas, rgbs, samples.t_starts, samples.t_ends,
                                                  samples.ray_offsets, 1e-4),
        "composite bwd": lambda: torch.autograd.grad(out[0], (sigmas, rgbs), g_rgb, retain_graph=True),
        "march+fwd+bwd": total,
        "same, capacity": total_no_sync,
        "_shape": (rays_o.shape[0], samples.n_samples),
    }


def device_times(fn, iters: int) -> tuple[float, list[tuple[str, float]]]:
    """(device seconds per call, [(kernel, seconds per call)] largest first) over ``iters`` calls."""
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(iters):
            fn()
        torch.cuda.synchronize()
    per_kernel = collections.Counter()
    for event in prof.events():
        if event.device_type == torch.autograd.DeviceType.CUDA:
            per_kernel[event.name[:40]] += event.device_time * 1e-6 / iters
    return sum(per_kernel.values()), per_kernel.most_common(3)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--samples", type=int, default=1 << 18)
    ap.add_argument("--iters", type=int, default=50)
    args = ap.parse_args()
    torch.manual_seed(0)
    print(f"{'scene':<7} {'op':<14} {'rays':>6} {'samples':>7} {'wall ms':>8} {'device ms':>9}  top kernels (ms)")
    for kind in ("sphere", "shell"):
        ops = scene_ops(kind, args.device, args.samples)
        n_rays, n_samples = ops.pop("_shape")
        for name, fn in ops.items():
            wall = timed(fn, args.iters, args.device)
            busy, top = device_times(fn, args.iters)
            kernels = ", ".join(f"{k} {1e3 * t:.3f}" for k, t in top)
            print(f"{kind:<7} {name:<14} {n_rays:>6} {n_samples:>7} {1e3 * wall:>8.3f} {1e3 * busy:>9.3f}  {kernels}")


if __name__ == "__main__":
    main()
