"""Regularisers on packed samples (as returned by ``render_rays(..., return_samples=True)``)."""

from __future__ import annotations

import torch


def distortion_loss(weights: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor,
                    ray_indices: torch.Tensor, n_rays: int) -> torch.Tensor:
    """Mip-NeRF 360's distortion loss of every ray, [n_rays] float32.

    .. math::
        L_r = \\sum_{i,j} w_i w_j \\left|m_i - m_j\\right| + \\tfrac13 \\sum_i w_i^2 \\delta_i
            = 2 \\sum_i w_i \\bigl(m_i W_{<i} - (wm)_{<i}\\bigr) + \\tfrac13 \\sum_i w_i^2 \\delta_i

    with interval midpoints :math:`m_i`, widths :math:`\\delta_i` and prefix sums over the ray's
    earlier samples (samples sorted by ray, front to back). Rows with ray index ``n_rays``
    (padding) are ignored.
    """
    w = weights.double()
    m = 0.5 * (t_starts + t_ends).double()
    width = (t_ends - t_starts).double()
    ray = ray_indices.long()
    wm = w * m

    def prefix_in_ray(x: torch.Tensor) -> torch.Tensor:
        # Exclusive prefix sums within each ray: the global one minus the sums of earlier rays.
        # (1-D scans only: torch scans a [S, 2] tensor along dim 0 with one thread per column.)
        per_ray = torch.zeros(n_rays + 1, dtype=torch.float64, device=x.device).index_add_(0, ray, x)
        return torch.cumsum(x, 0) - x - (torch.cumsum(per_ray, 0) - per_ray)[ray]

    w_before, wm_before = prefix_in_ray(w), prefix_in_ray(wm)
    inner = 2.0 * w * (m * w_before - wm_before) + w * w * width / 3.0
    loss = torch.zeros(n_rays + 1, dtype=torch.float64, device=w.device).index_add_(0, ray, inner)
    return loss[:n_rays].float()
