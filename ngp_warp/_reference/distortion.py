"""Float64 pure-torch twin of :func:`ngp_warp.ops.distortion.distortion_loss` (tests only)."""

from __future__ import annotations

import torch


def distortion_loss(weights, t_starts, t_ends, ray_indices, n_rays: int, near: float = 0.0) -> torch.Tensor:
    """[n_rays] float64 distortion loss straight from the double sum, one ray at a time (with
    ``near`` > 0 on s = 1 − near / max(t, near))."""
    if near > 0:
        t_starts, t_ends = (1 - near / t.double().clamp(min=near) for t in (t_starts, t_ends))
    out = []
    for r in range(n_rays):
        s = ray_indices == r
        w = weights[s].double()
        m = 0.5 * (t_starts[s] + t_ends[s]).double()
        d = (t_ends[s] - t_starts[s]).double()
        out.append((w[:, None] * w[None] * (m[:, None] - m[None]).abs()).sum() + (w * w * d).sum() / 3)
    return torch.stack(out) if out else torch.zeros(0, dtype=torch.float64)
