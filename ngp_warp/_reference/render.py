"""Float64 closed-form twin of :func:`ngp_warp.render_rays` for a sphere of constant density
(tests only)."""

from __future__ import annotations

import torch

f64 = torch.float64


def render_rays(rays_o, rays_d, center, radius: float, sigma: float):
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
