"""Float64 pure-torch twins of :class:`ngp_warp.OccupancyGrid`'s cascade geometry, update and
visibility marking (tests only)."""

from __future__ import annotations

import torch

from ngp_warp._reference.contraction import uncontract

f64 = torch.float64


def center_half(aabb):
    aabb = torch.as_tensor(aabb, dtype=f64)
    return (aabb[:3] + aabb[3:]) / 2, (aabb[3:] - aabb[:3]) / 2


def cascade_cells(points: torch.Tensor, aabb, resolution: int, levels: int):
    """Cell id of each point (finest cascade containing it, clamped) and its distance to the
    nearest cell face in cell units (small = float32 code may legitimately disagree)."""
    c, h = center_half(aabb)
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


def cell_boxes(aabb, resolution: int, levels: int):
    """[levels·R³, 2, 3] float64 lower and upper corners of every cell."""
    c, h = center_half(aabb)
    r = resolution
    ar = torch.arange(r, dtype=f64)
    ijk = torch.stack(torch.meshgrid(ar, ar, ar, indexing="ij"), -1).reshape(-1, 3)
    boxes = []
    for l in range(levels):
        s = h * 2.0**l
        lo = c - s + ijk * (2 * s / r)
        boxes.append(torch.stack([lo, lo + 2 * s / r], 1))
    return torch.cat(boxes)


def update(occs, cells, values, ema_decay: float, occ_threshold: float):
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


def project(points, c2w, intrinsics):
    """Points [..., 3] float64 seen by one OpenGL camera (c2w [3+, 4], intrinsics [4] fx fy cx
    cy): (u, v, depth, distance), each [...]; u = fx·x/(−z) + cx, v = cy − fy·y/(−z)."""
    fx, fy, cx, cy = intrinsics
    d = points - c2w[:3, 3]
    cam = d @ c2w[:3, :3]
    depth = -cam[..., 2]
    return fx * cam[..., 0] / depth + cx, cy - fy * cam[..., 1] / depth, depth, d.norm(dim=-1)


def visible_cells(aabb, resolution, levels, c2w, intrinsics, width, height, near_plane=0.0,
                  contraction=None, inner_aabb=None):
    """[levels·R³] bool: some corner of the cell projects into some OpenGL camera's image (with a
    contraction, the grid is in contracted space and the corners are uncontracted first)."""
    boxes = cell_boxes(aabb, resolution, levels)
    sel = torch.tensor([[i & 1, (i >> 1) & 1, i >> 2] for i in range(8)])
    corners = torch.stack([boxes[:, sel[:, a], a] for a in range(3)], -1)  # [n, 8, 3]
    if contraction is not None:
        inner = torch.as_tensor(inner_aabb, dtype=f64)
        corners = uncontract(corners.reshape(-1, 3), contraction, inner).reshape(corners.shape)
    seen = torch.zeros(boxes.shape[0], dtype=torch.bool)
    for m, intr in zip(c2w.to(f64).cpu(), intrinsics.to(f64).cpu()):
        u, v, depth, _ = project(corners, m, intr)
        ok = (depth > near_plane) & (depth > 0)
        ok &= (u >= 0) & (u <= width) & (v >= 0) & (v <= height)
        seen |= ok.any(-1)
    return seen


def zero_unseen(points, values, c2w, intrinsics, width, height, near=0.0, margin=0.0):
    """values [M] float64 with 0 where no OpenGL camera sees points [M, 3]: in its image grown by
    margin pixels, in front of it and farther than near from it."""
    p = points.to(f64).cpu()
    seen = torch.zeros(p.shape[0], dtype=torch.bool)
    for m, intr in zip(c2w.to(f64).cpu(), intrinsics.to(f64).cpu()):
        u, v, depth, distance = project(p, m, intr)
        ok = (depth > 0) & (distance > near)
        seen |= ok & (u >= -margin) & (u <= width + margin) & (v >= -margin) & (v <= height + margin)
    return torch.where(seen, values.to(f64).cpu(), torch.zeros((), dtype=f64))
