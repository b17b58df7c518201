"""Float64 pure-torch twins of the render kernels: occupancy grid, ray marching, compositing.

Slow and simple on purpose (per-ray loops, dense sampling); tests and benchmarks only.
"""

from __future__ import annotations

import torch

f64 = torch.float64


# -- compositing ---------------------------------------------------------------------------------
def ray_offsets_ref(ray_indices: torch.Tensor, n_rays: int) -> torch.Tensor:
    """[S] sorted ray indices → [n_rays + 1] int64 offsets."""
    return torch.searchsorted(ray_indices.long(), torch.arange(n_rays + 1, device=ray_indices.device))


def _ray_terms(sigmas, t_starts, t_ends, early_stop_eps):
    """Per-sample δ, α, T, T_next and the contribution mask of one ray (float64)."""
    delta = (t_ends - t_starts).to(f64)
    x = sigmas.to(f64) * delta
    alpha = -torch.expm1(-x)
    tau = torch.cumsum(x, 0)
    trans = torch.exp(-(tau - x))
    keep = (trans >= early_stop_eps).to(f64)
    return delta, alpha, trans, torch.exp(-tau), keep


def composite_ref(sigmas, rgbs, t_starts, t_ends, ray_indices, n_rays: int, early_stop_eps: float = 0.0):
    """Float64 loop over rays; differentiable by autograd. Returns rgb, opacity, depth, weights."""
    offsets = ray_offsets_ref(ray_indices, n_rays).tolist()
    rgb, opacity, depth, weights = [], [], [], []
    for r in range(n_rays):
        s = slice(offsets[r], offsets[r + 1])
        _, alpha, trans, _, keep = _ray_terms(sigmas[s], t_starts[s], t_ends[s], early_stop_eps)
        w = trans * alpha * keep
        mid = 0.5 * (t_starts[s] + t_ends[s]).to(f64)
        rgb.append((w[:, None] * rgbs[s].to(f64)).sum(0))
        opacity.append(w.sum())
        depth.append((w * mid).sum())
        weights.append(w)
    z = torch.zeros(0, dtype=f64, device=sigmas.device)
    return (
        torch.stack(rgb) if rgb else z.reshape(0, 3),
        torch.stack(opacity) if opacity else z,
        torch.stack(depth) if depth else z,
        torch.cat(weights) if weights else z,
    )


def contributing_ref(sigmas, t_starts, t_ends, ray_indices, n_rays: int, early_stop_eps: float):
    """[S] bool: the samples that composite (transmittance in front ≥ eps) and [S] float64 T."""
    offsets = ray_offsets_ref(ray_indices, n_rays).tolist()
    keep, trans = [], []
    for r in range(n_rays):
        s = slice(offsets[r], offsets[r + 1])
        _, _, t, _, k = _ray_terms(sigmas[s], t_starts[s], t_ends[s], early_stop_eps)
        keep.append(k.bool())
        trans.append(t)
    return torch.cat(keep), torch.cat(trans)


def composite_backward_ref(sigmas, rgbs, t_starts, t_ends, ray_indices, n_rays, g_rgb, g_opacity, g_depth,
                           g_weights=None, early_stop_eps: float = 0.0):
    """Twin of the backward kernel: with v_i = c_i·g_C + m_i g_D + g_O + g_w_i,
    dL/dc_i = w_i g_C and dL/dσ_i = δ_i (T_{i+1} v_i − Σ_{j>i} w_j v_j)."""
    offsets = ray_offsets_ref(ray_indices, n_rays).tolist()
    g_sigmas, g_rgbs = [], []
    for r in range(n_rays):
        s = slice(offsets[r], offsets[r + 1])
        delta, alpha, trans, trans_next, keep = _ray_terms(sigmas[s], t_starts[s], t_ends[s], early_stop_eps)
        w = trans * alpha * keep
        mid = 0.5 * (t_starts[s] + t_ends[s]).to(f64)
        v = rgbs[s].to(f64) @ g_rgb[r].to(f64) + mid * g_depth[r].to(f64) + g_opacity[r].to(f64)
        if g_weights is not None:
            v = v + g_weights[s].to(f64)
        wv = w * v
        suffix = torch.flip(torch.cumsum(torch.flip(wv, [0]), 0), [0]) - wv
        g_sigmas.append(delta * (trans_next * keep * v - suffix))
        g_rgbs.append(w[:, None] * g_rgb[r].to(f64))
    return torch.cat(g_sigmas), torch.cat(g_rgbs)


# -- occupancy grid ------------------------------------------------------------------------------
def _center_half(aabb):
    aabb = torch.as_tensor(aabb, dtype=f64)
    return (aabb[:3] + aabb[3:]) / 2, (aabb[3:] - aabb[:3]) / 2


def cascade_cells_ref(points: torch.Tensor, aabb, resolution: int, levels: int):
    """Cell id of each point (finest cascade containing it, clamped) and its distance to the
    nearest cell face in cell units (small = float32 code may legitimately disagree)."""
    c, h = _center_half(aabb)
    q = points.to(f64).cpu() - c
    m = (q.abs() / h).amax(-1)
    level = torch.full((q.shape[0],), levels - 1, dtype=torch.long)
    for l in reversed(range(levels)):
        level = torch.where(m <= 2.0**l, torch.full_like(level, l), level)
    scale = torch.pow(2.0, level.to(f64))[:, None]
    f = (q / (h * scale) * 0.5 + 0.5) * resolution
    frac = f - torch.floor(f)
    margin = torch.minimum(frac, 1 - frac).amin(-1)
    ijk = torch.floor(f).long().clamp(0, resolution - 1)
    ids = ((level * resolution + ijk[:, 0]) * resolution + ijk[:, 1]) * resolution + ijk[:, 2]
    return ids, margin


def cell_boxes_ref(aabb, resolution: int, levels: int):
    """[levels·R³, 2, 3] float64 lower and upper corners of every cell."""
    c, h = _center_half(aabb)
    r = resolution
    ar = torch.arange(r, dtype=f64)
    ijk = torch.stack(torch.meshgrid(ar, ar, ar, indexing="ij"), -1).reshape(-1, 3)
    boxes = []
    for l in range(levels):
        s = h * 2.0**l
        lo = c - s + ijk * (2 * s / r)
        boxes.append(torch.stack([lo, lo + 2 * s / r], 1))
    return torch.cat(boxes)


def occupancy_update_ref(occs, cells, values, ema_decay: float, occ_threshold: float):
    """One update from sampled (cell, value) pairs: scatter-max, max-EMA on visible cells,
    threshold = min(occ_threshold, mean visible occ). Returns occs, threshold, occupied."""
    occs = occs.to(f64).cpu().clone()
    splat = torch.full_like(occs, -1.0).scatter_reduce(0, cells.long().cpu(), values.to(f64).cpu().clamp(min=0), "amax")
    upd = (splat >= 0) & (occs >= 0)
    occs[upd] = torch.maximum(occs[upd] * ema_decay, splat[upd])
    vis = occs >= 0
    mean = occs[vis].mean() if vis.any() else torch.zeros((), dtype=f64)
    thr = torch.clamp(mean, max=occ_threshold)
    return occs, thr, occs > thr


def visible_cells_ref(aabb, resolution, levels, c2w, intrinsics, width, height, near_plane=0.0):
    """[levels·R³] bool: some corner of the cell projects into some OpenGL camera's image."""
    boxes = cell_boxes_ref(aabb, resolution, levels)
    sel = torch.tensor([[i & 1, (i >> 1) & 1, i >> 2] for i in range(8)])
    corners = torch.stack([boxes[:, sel[:, a], a] for a in range(3)], -1)  # [n, 8, 3]
    seen = torch.zeros(boxes.shape[0], dtype=torch.bool)
    for m, (fx, fy, cx, cy) in zip(c2w.to(f64).cpu(), intrinsics.to(f64).cpu()):
        cam = (corners - m[:3, 3]) @ m[:3, :3]
        depth = -cam[..., 2]
        ok = (depth > near_plane) & (depth > 0)
        u = fx * cam[..., 0] / depth + cx
        v = cy - fy * cam[..., 1] / depth
        ok &= (u >= 0) & (u <= width) & (v >= 0) & (v <= height)
        seen |= ok.any(-1)
    return seen


# -- ray marching ------------------------------------------------------------------------------
def ray_box_ref(rays_o, rays_d, lo, hi):
    """(t_enter, t_exit) of each ray with the box [lo, hi] (t_enter > t_exit on a miss)."""
    o, d = rays_o.to(f64).cpu(), rays_d.to(f64).cpu()
    lo, hi = torch.as_tensor(lo, dtype=f64), torch.as_tensor(hi, dtype=f64)
    with torch.no_grad():
        inv = 1.0 / d
        ta, tb = (lo - o) * inv, (hi - o) * inv
        t_in = torch.minimum(ta, tb).nan_to_num(-torch.inf).amax(-1)
        t_out = torch.maximum(ta, tb).nan_to_num(torch.inf).amin(-1)
    return t_in, t_out


def march_ref(rays_o, rays_d, aabb, occupied: torch.Tensor, *, near=0.0, far=1e10, step=0.01,
              cone_angle=0.0, max_step=1e10):
    """Dense sampler: every step t_k in [t0, t1] of each ray, whether or not its cell is occupied.

    Returns a dict of flat float64/long tensors sorted by (ray, t): ray, t_start, t_end,
    occupied (cell of the midpoint), margin (distance of the midpoint to a cell face, cells).
    """
    levels, res = occupied.shape[0], occupied.shape[1]
    c, h = _center_half(aabb)
    outer = h * 2.0 ** (levels - 1)
    t_in, t_out = ray_box_ref(rays_o, rays_d, c - outer, c + outer)
    t0, t1 = t_in.clamp(min=near), t_out.clamp(max=far)
    o, d = rays_o.to(f64).cpu(), rays_d.to(f64).cpu()
    rays, starts, ends = [], [], []
    k = 0
    t = t0.clone()
    active = (t0 < t1) & (d.abs().sum(-1) > 0)
    while active.any():
        dt = torch.full_like(t, step) if cone_angle == 0 else (t * cone_angle).clamp(step, max_step)
        idx = active.nonzero()[:, 0]
        rays.append(idx)
        starts.append(t[idx])
        ends.append(torch.minimum(t + dt, t1)[idx])
        k += 1
        t = t0 + k * step if cone_angle == 0 else t + dt
        active &= t < t1
    ray = torch.cat(rays) if rays else torch.zeros(0, dtype=torch.long)
    t_start = torch.cat(starts) if starts else torch.zeros(0, dtype=f64)
    t_end = torch.cat(ends) if ends else torch.zeros(0, dtype=f64)
    order = torch.argsort(ray, stable=True)
    ray, t_start, t_end = ray[order], t_start[order], t_end[order]
    mid = o[ray] + d[ray] * (0.5 * (t_start + t_end))[:, None]
    cells, margin = cascade_cells_ref(mid, aabb, res, levels)
    return {"ray": ray, "t_start": t_start, "t_end": t_end,
            "occupied": occupied.reshape(-1).cpu()[cells], "margin": margin}


# -- analytic scene ------------------------------------------------------------------------------
def sphere_render_ref(rays_o, rays_d, center, radius: float, sigma: float):
    """Opacity and depth of unit-direction rays through a sphere of constant density σ:
    O = 1 − e^{−σL}, D = a(1 − e^{−σL}) − L e^{−σL} + (1 − e^{−σL})/σ for the chord [a, a + L]."""
    o = rays_o.to(f64).cpu() - torch.as_tensor(center, dtype=f64)
    d = rays_d.to(f64).cpu()
    b = (o * d).sum(-1)
    disc = b * b - ((o * o).sum(-1) - radius**2)
    root = disc.clamp(min=0).sqrt()
    a = (-b - root).clamp(min=0)
    length = ((-b + root) - a).clamp(min=0) * (disc > 0)
    e = torch.exp(-sigma * length)
    return 1 - e, a * (1 - e) - length * e + (1 - e) / sigma
