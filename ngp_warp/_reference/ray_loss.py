"""Float64 pure-torch twin of :func:`ngp_warp.ops.ray_loss.ray_loss` (tests only)."""

from __future__ import annotations

import torch


def ray_loss(rgb, opacity, target, background, ray_mask=None, extra=None, extra_weight: float = 0.0,
             huber_delta: float | None = None, rays_per_pixel: int = 1):
    """(loss, mse) of :func:`ngp_warp.ops.ray_loss.ray_loss` in float64 torch (differentiable)."""
    k = rays_per_pixel
    rgb, opacity = rgb.double().view(-1, k, 3).mean(1), opacity.double().view(-1, k).mean(1)
    extra = None if extra is None else extra.double().view(-1, k).mean(1)
    ray_mask = None if ray_mask is None else ray_mask.view(-1, k).all(1)
    e = rgb + background.double() * (1 - opacity)[:, None] - target.double()
    if huber_delta is None:
        per_channel = e * e
    else:
        a = e.abs()
        per_channel = torch.where(a < huber_delta, 0.5 * e * e, huber_delta * (a - 0.5 * huber_delta))
    per_ray = per_channel.mean(-1)
    if extra is not None:
        per_ray = per_ray + extra_weight * extra.double()
    m = torch.ones_like(per_ray) if ray_mask is None else ray_mask.double()
    rays = m.sum().clamp_min(1)
    return (m * per_ray).sum() / rays, (m * (e * e).mean(-1)).sum() / rays
