"""Float64 twin of ``kernels/export.py`` (tests only)."""

from __future__ import annotations

import torch

from ngp_warp._reference.occupancy import cascade_cells, center_half


def points_occupied(points: torch.Tensor, aabb, resolution: int, levels: int, occupied: torch.Tensor):
    """Points [N, 3], the grid's unpacked bits ``occupied`` [levels, R, R, R] bool → [N] bool
    (whether each point's cell is occupied; points outside the coarsest cascade are empty),
    and each point's distance to its nearest cell face in cell units (float32 code may
    legitimately disagree where it is tiny)."""
    ids, margin = cascade_cells(points, aabb, resolution, levels)
    c, h = center_half(aabb)
    inside = ((points.double().cpu() - c).abs() <= h * 2.0 ** (levels - 1)).all(-1)
    return occupied.reshape(-1).cpu()[ids] & inside, margin
