"""Nerfacc's volume-rendering helpers on packed samples, for porting code written against it:
per-sample alphas and transmittance, sums along rays, and ``rendering`` with a callback that
sees each sample's interval and ray. Pure torch (differentiable to any order); the hot path
stays :func:`ngp_warp.composite` (Warp kernels).

For the samples :math:`i` of one ray, front to back,

.. math::

    \\alpha_i = 1 - e^{-\\sigma_i (t^{end}_i - t^{start}_i)}, \\qquad
    T_i = \\prod_{j<i} (1 - \\alpha_j) = e^{-\\sum_{j<i} \\sigma_j \\delta_j}, \\qquad
    w_i = T_i \\alpha_i.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from ngp_warp.ops.composite import composite


def _check_packed(sigmas: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor, ray_indices: torch.Tensor,
                  n_rays: int) -> None:
    n = sigmas.shape[0] if isinstance(sigmas, torch.Tensor) else -1
    for name, t in (("sigmas", sigmas), ("t_starts", t_starts), ("t_ends", t_ends), ("ray_indices", ray_indices)):
        if not isinstance(t, torch.Tensor) or tuple(t.shape) != (n,):
            raise ValueError(f"{name} must be a [S] tensor like sigmas, got {getattr(t, 'shape', type(t).__name__)}")
    if not isinstance(n_rays, int) or n_rays < 0:
        raise ValueError(f"n_rays must be a non-negative int, got {n_rays!r}")


def alphas_and_transmittance(sigmas: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor,
                             ray_indices: torch.Tensor, n_rays: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(alphas [S], transmittance [S]) of packed samples (nerfacc's
    ``render_transmittance_from_density`` and alphas): :math:`\\alpha_i` and :math:`T_i` above,
    the optical depth summed per ray in float64, differentiable in ``sigmas``.

    Args:
        sigmas: [S] float densities ≥ 0. t_starts, t_ends: [S] float intervals.
        ray_indices: [S] int64, sorted (each ray's samples contiguous, front to back), in [0, n_rays).
        n_rays: number of rays.
    """
    _check_packed(sigmas, t_starts, t_ends, ray_indices, n_rays)
    depth = sigmas * (t_ends - t_starts)
    total = torch.cumsum(depth.double(), 0)
    first = torch.searchsorted(ray_indices.long(), torch.arange(n_rays, device=ray_indices.device))
    before_ray = torch.nn.functional.pad(total, (1, 0))[first]  # optical depth before each ray's first sample
    in_front = total - depth.double() - before_ray[ray_indices.long()]
    return -torch.expm1(-depth), torch.exp(-in_front).to(sigmas.dtype)


def accumulate_along_rays(weights: torch.Tensor, values: torch.Tensor | None, ray_indices: torch.Tensor,
                          n_rays: int) -> torch.Tensor:
    """Σ over each ray's samples of ``weights`` × ``values`` (nerfacc's ``accumulate_along_rays``):
    weights [S], values [S, C] (None: ones, giving the opacity as [n_rays, 1]), ray_indices [S]
    int64 in [0, n_rays) → [n_rays, C], differentiable in weights and values."""
    if values is None:
        values = torch.ones_like(weights)[:, None]
    if weights.dim() != 1 or values.dim() != 2 or values.shape[0] != weights.shape[0] \
            or tuple(ray_indices.shape) != tuple(weights.shape):
        raise ValueError(f"weights must be [S], values [S, C] and ray_indices [S], got {tuple(weights.shape)}, "
                         f"{tuple(values.shape)} and {tuple(ray_indices.shape)}")
    out = torch.zeros(n_rays, values.shape[1], dtype=values.dtype, device=values.device)
    return out.index_add(0, ray_indices.long(), weights[:, None] * values)


RgbSigmaFn = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]


def rendering(t_starts: torch.Tensor, t_ends: torch.Tensor, ray_indices: torch.Tensor, n_rays: int,
              rgb_sigma_fn: RgbSigmaFn, render_bkgd: torch.Tensor | None = None,
              early_stop_eps: float = 0.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict]:
    """Nerfacc's ``rendering``: colour the packed samples through a callback that sees their
    intervals and rays, and composite them with the Warp kernels.

    Args:
        t_starts, t_ends: [S] float32 intervals (differentiable, as nerfacc's: through the
            callback, σ·δ and the depth); ray_indices: [S] int64 sorted, as
            :func:`ngp_warp.ray_marching` returns them.
        n_rays: number of rays.
        rgb_sigma_fn: ``(t_starts [S], t_ends [S], ray_indices [S]) → (rgbs [S, 3], sigmas [S])``.
        render_bkgd: None, or [3] / [n_rays, 3] colour blended behind.
        early_stop_eps: as :func:`ngp_warp.composite`.

    Returns:
        (colors [n_rays, 3], opacities [n_rays, 1], depths [n_rays, 1], extras) with extras
        ``weights``, ``alphas``, ``trans`` (each [S]), as nerfacc's.
    """
    rgbs, sigmas = rgb_sigma_fn(t_starts, t_ends, ray_indices)
    sigmas = sigmas.reshape(-1)
    rgb, opacity, depth, weights = composite(sigmas, rgbs, t_starts, t_ends, ray_indices, n_rays,
                                             early_stop_eps=early_stop_eps, return_weights=True)
    if render_bkgd is not None:
        rgb = rgb + render_bkgd * (1.0 - opacity[:, None])
    alphas, trans = alphas_and_transmittance(sigmas, t_starts, t_ends, ray_indices, n_rays)
    return rgb, opacity[:, None], depth[:, None], {"weights": weights, "alphas": alphas, "trans": trans}
