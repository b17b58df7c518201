"""Kernel throughput: the benchmark scenes and timers, and the ``ngp-warp bench`` table.

Shared by ``ngp-warp bench`` (:func:`run_kernel_bench`) and the scripts in ``benchmarks/``:

* :func:`measure` times the hash-grid encoding (forward, backward to the table, both) on
  uniform random points in the unit cube (the worst case for the caches);
* :func:`bench_scene` times the render op (ray marching, compositing forward and backward,
  and all three) on rays from radius 3 aimed into a sphere of radius ``RADIUS`` in the box
  ``AABB`` = [-1, 1]^3 (128³ occupancy grid, default step): ``sphere`` occupies the solid
  sphere, ``shell`` a thin shell around its surface like a trained grid (~30 samples per ray).

Every time is seconds per call after warm-up with the device synchronised: on the CPU by
``perf_counter``, on CUDA between two CUDA events around a batch of back-to-back calls (so the
host-side cost of a call overlaps the GPU work of the previous ones, as in training).
"""

from __future__ import annotations

import platform
import statistics
import time
from dataclasses import dataclass

import torch

from ngp_warp import _wp
from ngp_warp.ops.graphs import capture_graph
from ngp_warp.ops.hashgrid import HashGridEncoding
from ngp_warp.ops.occupancy import OccupancyGrid
from ngp_warp.ops.raymarch import ray_marching
from ngp_warp.ops.render import composite_packed

AABB = torch.tensor([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0])
RADIUS = 0.6


def device_name(device: torch.device | str) -> str:
    """The GPU's name on CUDA, else the host processor (as ``platform`` reports it)."""
    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return platform.processor() or platform.machine()


def timer(device: torch.device, fn, repeats: int, warmup: int, inner: int) -> float:
    """Median seconds per call of ``fn``, timed over ``repeats`` batches of ``inner`` back-to-back
    calls after ``warmup`` calls.

    On a GPU the calls of a batch are queued back to back between two CUDA events, so that the
    host's per-call overhead (Python, argument wrapping, launch) overlaps the GPU work as in a
    training loop instead of being counted as idle GPU time.
    """
    for _ in range(warmup):
        fn()
    times = []
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        stream = torch.cuda.current_stream(device)  # the stream ngp_warp launches on
        for _ in range(repeats):
            start = torch.cuda.Event(enable_timing=True)
            end = torch.cuda.Event(enable_timing=True)
            start.record(stream)
            for _ in range(inner):
                fn()
            end.record(stream)
            end.synchronize()
            times.append(start.elapsed_time(end) * 1e-3 / inner)
    else:
        for _ in range(repeats):
            t0 = time.perf_counter()
            for _ in range(inner):
                fn()
            times.append((time.perf_counter() - t0) / inner)
    return statistics.median(times)


def timed(fn, iters: int, device: str) -> float:
    """Seconds per call of ``fn``, averaged over ``iters`` calls after two warm-up calls."""
    return timer(torch.device(device), fn, repeats=1, warmup=2, inner=iters)


def measure(enc, encode, params, n: int, device, repeats: int, warmup: int, inner: int, with_dx: bool) -> dict:
    """Times of fwd / bwd / f+b (and bwdx) for ``encode(x, params)`` on two alternating inputs.

    ``enc`` gives the dimensions (``n_input_dims``, ``n_output_dims``); ``x`` is ``[n, D]``
    uniform in the unit cube. Returns seconds per call under ``fwd_s`` (no grad), ``bwd_s``
    (backward to ``params``), ``fb_s`` (both) and, with ``with_dx``, ``bwdx_s`` (backward to x).
    """
    device = torch.device(device)
    D = enc.n_input_dims
    xs = [torch.rand(n, D, device=device) for _ in range(2)]
    g = torch.randn(n, enc.n_output_dims, device=device)
    state = {"i": 0}

    def next_x():
        state["i"] ^= 1
        return xs[state["i"]]

    def fwd():
        with torch.no_grad():
            encode(next_x(), params)

    ys = [encode(x, params) for x in xs]

    def bwd():
        state["i"] ^= 1
        torch.autograd.grad(ys[state["i"]], params, g, retain_graph=True)

    def fwd_bwd():
        torch.autograd.grad(encode(next_x(), params), params, g)

    out = {
        "fwd_s": timer(device, fwd, repeats, warmup, inner),
        "bwd_s": timer(device, bwd, repeats, warmup, inner),
        "fb_s": timer(device, fwd_bwd, repeats, warmup, inner),
    }
    del ys
    if with_dx:
        xg = [x.clone().requires_grad_() for x in xs]
        ys = [encode(x, params.detach()) for x in xg]

        def bwdx():
            state["i"] ^= 1
            torch.autograd.grad(ys[state["i"]], xg[state["i"]], g, retain_graph=True)

        out["bwdx_s"] = timer(device, bwdx, repeats, warmup, inner)
    return out


def scene_grid(kind: str, device: str) -> OccupancyGrid:
    """A 128³ grid over ``AABB`` occupying the solid sphere (``"sphere"``) or a thin shell
    ``| |p| - RADIUS | < 0.02`` (any other ``kind``)."""
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


def bench_scene(kind: str, device: str, target_samples: int, iters: int) -> list[dict]:
    """Rows ``{scene, op, device, rays, samples, ms, rays_per_s, samples_per_s}`` for the ops
    ``march``, ``composite fwd``, ``composite bwd`` and ``march+fwd+bwd`` on as many rays of the
    scene ``kind`` as give about ``target_samples`` samples, each timed by :func:`timed`; and
    ``same, capacity``: all three with the march given a capacity 1/8 above the count (no host
    synchronisation, so back-to-back calls overlap the host's work with the GPU's); on CUDA
    ``same, CUDA graph``: that call captured once and replayed (:func:`ngp_warp.ops.graphs.capture_graph`)."""
    grid = scene_grid(kind, device)
    probe_o, probe_d = make_rays(1024, device)
    per_ray = max(ray_marching(probe_o, probe_d, grid, validate=False).n_samples / 1024, 1.0)
    n_rays = max(1, round(target_samples / per_ray))
    rays_o, rays_d = make_rays(n_rays, device)
    samples = ray_marching(rays_o, rays_d, grid, validate=False)
    s = samples.n_samples
    sigmas = (torch.rand(s, device=device) * 2).requires_grad_(True)
    rgbs = torch.rand(s, 3, device=device).requires_grad_(True)
    g_rgb = torch.rand(n_rays, 3, device=device)

    def march():
        return ray_marching(rays_o, rays_d, grid, validate=False)

    def forward():
        return composite_packed(sigmas, rgbs, samples.t_starts, samples.t_ends, samples.ray_offsets, 1e-4)

    out = forward()

    def backward():
        torch.autograd.grad(out[0], (sigmas, rgbs), g_rgb, retain_graph=True)

    def total():
        m = march()
        rgb = composite_packed(sigmas, rgbs, m.t_starts, m.t_ends, m.ray_offsets, 1e-4)[0]
        torch.autograd.grad(rgb, (sigmas, rgbs), g_rgb)

    capacity = s + s // 8  # room for the count to vary, as a caller would size it from the last call
    sigmas_c = torch.cat([sigmas.detach(), sigmas.detach()[: capacity - s]]).requires_grad_(True)
    rgbs_c = torch.cat([rgbs.detach(), rgbs.detach()[: capacity - s]]).requires_grad_(True)

    def total_no_sync():
        m = ray_marching(rays_o, rays_d, grid, validate=False, capacity=capacity)
        rgb = composite_packed(sigmas_c, rgbs_c, m.t_starts, m.t_ends, m.ray_offsets, 1e-4)[0]
        torch.autograd.grad(rgb, (sigmas_c, rgbs_c), g_rgb)

    ops = [("march", march), ("composite fwd", forward), ("composite bwd", backward),
           ("march+fwd+bwd", total), ("same, capacity", total_no_sync)]
    if device.startswith("cuda"):
        ops.append(("same, CUDA graph", capture_graph(total_no_sync, device)[0].replay))
    rows = []
    for op, fn in ops:
        sec = timed(fn, iters, device)
        rows.append({"scene": kind, "op": op, "device": device, "rays": n_rays, "samples": s,
                     "ms": sec * 1e3, "rays_per_s": n_rays / sec, "samples_per_s": s / sec})
    return rows


@dataclass(frozen=True)
class KernelBenchConfig:
    """Sizes and repetitions of ``ngp-warp bench``."""

    points: int  # hash-grid batch (NeRF configuration L=16 F=2 T=2^19)
    samples: int  # target samples of the thin-shell render scene
    repeats: int  # encoding: timed batches (median)
    inner: int  # encoding: calls per batch
    iters: int  # render: timed calls (mean)

    @classmethod
    def for_device(cls, device: str, quick: bool) -> KernelBenchConfig:
        if device.startswith("cuda"):
            return cls(1 << 18, 1 << 16, 5, 5, 50) if quick else cls(1 << 20, 1 << 18, 20, 5, 200)
        return cls(1 << 12, 1 << 12, 2, 1, 3) if quick else cls(1 << 14, 1 << 14, 3, 1, 5)


def kernel_bench_rows(device: str, config: KernelBenchConfig) -> list[dict]:
    """Rows ``{op, n, ms, items_per_s}``: hash-grid encoding (items: points), then the render op
    on the thin-shell scene (items: samples)."""
    enc = HashGridEncoding(3, 16, 2, 19, 16, 2.0, device=device)
    t = measure(enc, lambda x, p: enc(x), enc.params, config.points, device, config.repeats, 2, config.inner, False)
    rows = [{"op": f"encode {name}", "n": config.points, "ms": t[key] * 1e3, "items_per_s": config.points / t[key]}
            for name, key in (("fwd", "fwd_s"), ("bwd", "bwd_s"), ("fwd+bwd", "fb_s"))]
    del enc
    for r in bench_scene("shell", device, config.samples, config.iters):
        rows.append({"op": r["op"], "n": r["samples"], "ms": r["ms"], "items_per_s": r["samples_per_s"]})
    return rows


def run_kernel_bench(device: str, quick: bool) -> None:
    """Print the ``ngp-warp bench`` table (op, N, ms per call, million items per second)."""
    config = KernelBenchConfig.for_device(device, quick)
    torch.manual_seed(0)
    threads = "" if device.startswith("cuda") else f", {_wp.cpu_threads()} threads"
    print(f"device: {device} ({device_name(device)}{threads})")
    rows = kernel_bench_rows(device, config)
    head = f"{'op':<16} {'N':>8} {'ms':>10} {'M items/s':>10}"
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r['op']:<16} {r['n']:>8} {r['ms']:>10.3f} {r['items_per_s'] / 1e6:>10.2f}")
    print("encode: hash grid L=16 F=2 T=2^19 on random points (items: points); march/composite: "
          "thin-shell scene (items: samples)")
