"""Float64 pure-torch twin of :func:`ngp_warp.ray_marching`: a dense sampler (tests only)."""

from __future__ import annotations

import math

import torch

from ngp_warp._reference import contraction as contraction_ref
from ngp_warp._reference.occupancy import cascade_cells, center_half

f64 = torch.float64


def ray_box(rays_o, rays_d, lo, hi):
    """(t_enter, t_exit) of each ray with the box [lo, hi] (t_enter > t_exit on a miss)."""
    o, d = rays_o.to(f64).cpu(), rays_d.to(f64).cpu()
    lo, hi = torch.as_tensor(lo, dtype=f64), torch.as_tensor(hi, dtype=f64)
    with torch.no_grad():
        inv = 1.0 / d
        ta, tb = (lo - o) * inv, (hi - o) * inv
        t_in = torch.minimum(ta, tb).nan_to_num(-torch.inf).amax(-1)
        t_out = torch.maximum(ta, tb).nan_to_num(torch.inf).amin(-1)
    return t_in, t_out


def step_starts(t0: torch.Tensor, k: int, step: float, cone_angle: float, max_step: float) -> torch.Tensor:
    """t_k of t_{k+1} = t_k + clip(t_k·cone_angle, step, max_step) from t0 ([N] float64), in
    closed form as the kernel: t0 + k·step while t_k·cone_angle ≤ step (the first k_cone steps),
    then t_cone·(1 + cone_angle)^(k − k_cone) while below max_step (up to k_max), then
    t_max + (k − k_max)·max_step."""
    if cone_angle == 0:
        return t0 + k * step
    k_cone = torch.where(t0 <= step / cone_angle, torch.floor((step / cone_angle - t0) / step) + 1, 0.0)
    t_cone = t0 + k_cone * step
    growth = math.log1p(cone_angle)
    growing = torch.ceil(torch.log(max_step / cone_angle / t_cone) / growth).clamp(min=0.0)
    t_max = t_cone * torch.exp(growing * growth)
    k_max = k_cone + growing
    return torch.where(k < k_cone, t0 + k * step,
                       torch.where(k < k_max, t_cone * torch.exp((k - k_cone) * growth), t_max + (k - k_max) * max_step))


def ray_marching(rays_o, rays_d, aabb, occupied: torch.Tensor, *, near=0.0, far=1e10, step=0.01,
              cone_angle=0.0, max_step=1e10):
    """Dense sampler: every step t_k in [t0, t1] of each ray, whether or not its cell is occupied.

    Returns a dict of flat float64/long tensors sorted by (ray, t): ray, t_start, t_end,
    occupied (cell of the midpoint), margin (distance of the midpoint to a cell face, cells).
    """
    levels, res = occupied.shape[0], occupied.shape[1]
    c, h = center_half(aabb)
    outer = h * 2.0 ** (levels - 1)
    t_in, t_out = ray_box(rays_o, rays_d, c - outer, c + outer)
    t0, t1 = t_in.clamp(min=near), t_out.clamp(max=far)
    o, d = rays_o.to(f64).cpu(), rays_d.to(f64).cpu()
    rays, starts, ends = [], [], []
    k = 0
    t = t0.clone()
    active = (t0 < t1) & (d.abs().sum(-1) > 0)
    while active.any():
        t_next = step_starts(t0, k + 1, step, cone_angle, max_step)
        idx = active.nonzero()[:, 0]
        rays.append(idx)
        starts.append(t[idx])
        ends.append(torch.minimum(t_next, t1)[idx])
        k += 1
        t = t_next
        active &= t < t1
    ray = torch.cat(rays) if rays else torch.zeros(0, dtype=torch.long)
    t_start = torch.cat(starts) if starts else torch.zeros(0, dtype=f64)
    t_end = torch.cat(ends) if ends else torch.zeros(0, dtype=f64)
    order = torch.argsort(ray, stable=True)
    ray, t_start, t_end = ray[order], t_start[order], t_end[order]
    mid = o[ray] + d[ray] * (0.5 * (t_start + t_end))[:, None]
    cells, margin = cascade_cells(mid, aabb, res, levels)
    return {"ray": ray, "t_start": t_start, "t_end": t_end,
            "occupied": occupied.reshape(-1).cpu()[cells], "margin": margin}


def ray_marching_contracted(rays_o, rays_d, inner_aabb, kind: str, occupied: torch.Tensor, *, near=0.0,
                            far=1e10, step=0.01, cone_angle=0.0, max_step=1e10):
    """Dense sampler of a contracted grid (one cascade over [-2, 2]³): every world step over
    [near, far], Δt = max(step / ‖J_C(x)(d ⊘ h)‖, min(t·cone_angle, max_step)) (the speed from
    autograd, :func:`ngp_warp._reference.contraction.world_step_length`), occupied where the
    cell of C(midpoint) is. Returns the dict of :func:`ray_marching`."""
    res = occupied.shape[1]
    o, d = rays_o.to(f64).cpu(), rays_d.to(f64).cpu()
    inner = torch.as_tensor(inner_aabb, dtype=f64)
    t = torch.full((o.shape[0],), float(near), dtype=f64)
    active = d.abs().sum(-1) > 0
    rays, starts, ends = [], [], []
    while active.any():
        idx = active.nonzero()[:, 0]
        dt = contraction_ref.world_step_length(o[idx] + d[idx] * t[idx, None], d[idx], step, kind, inner)
        if cone_angle > 0:
            dt = torch.maximum(dt, (t[idx] * cone_angle).clamp(max=max_step))
        rays.append(idx)
        starts.append(t[idx])
        ends.append(torch.clamp(t[idx] + dt, max=far))
        t[idx] = t[idx] + dt
        active &= t < far
    ray, t_start, t_end = torch.cat(rays), torch.cat(starts), torch.cat(ends)
    order = torch.argsort(ray, stable=True)
    ray, t_start, t_end = ray[order], t_start[order], t_end[order]
    mid = o[ray] + d[ray] * (0.5 * (t_start + t_end))[:, None]
    y = contraction_ref.contract(mid, kind, inner)
    cells, margin = cascade_cells(y, [-2.0] * 3 + [2.0] * 3, res, 1)
    return {"ray": ray, "t_start": t_start, "t_end": t_end,
            "occupied": occupied.reshape(-1).cpu()[cells], "margin": margin}
