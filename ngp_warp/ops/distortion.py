"""Mip-NeRF 360's distortion loss of packed samples (as ``render_rays(..., return_samples=True)``
returns them): a Warp forward and a hand-written backward."""

from __future__ import annotations

import torch

from ngp_warp import _wp
from ngp_warp._checks import check_distances
from ngp_warp.ops._differentiable_once import refuse_second_derivative
from ngp_warp.kernels import distortion as K

_BLOCK = 32  # one thread per ray, as in ngp_warp.ops.composite


class _Distortion(torch.autograd.Function):
    """The Warp forward and hand-written backward of :func:`distortion_loss`."""

    @staticmethod
    def forward(ctx, weights, t_starts, t_ends, offsets, near):
        n_rays = offsets.shape[0] - 1
        loss = torch.empty(n_rays, dtype=torch.float32, device=weights.device)
        _wp.launch(K.distortion_forward, n_rays, [weights, t_starts, t_ends, offsets, near, loss],
                   _wp.device_of(weights), block_dim=_BLOCK)
        ctx.save_for_backward(weights, t_starts, t_ends, offsets)
        ctx.near = near
        return loss

    @staticmethod
    def backward(ctx, grad_loss):
        weights, t_starts, t_ends, offsets = ctx.saved_tensors
        intervals = any(ctx.needs_input_grad[1:3])
        grad = torch.zeros_like(weights)  # rows of no ray (padding) get none
        grad_t = (torch.zeros_like(t_starts), torch.zeros_like(t_ends)) if intervals else (None, None)
        _wp.launch(K.distortion_backward, offsets.shape[0] - 1,
                   [weights, t_starts, t_ends, offsets, ctx.near, grad_loss.detach().float().contiguous(),
                    int(intervals), grad, *grad_t],
                   _wp.device_of(weights), block_dim=_BLOCK)
        grads = refuse_second_derivative("distortion_loss", (grad, *grad_t), (weights, t_starts, t_ends, grad_loss))
        return *grads, None, None


def distortion_loss_packed(weights: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor,
                           ray_offsets: torch.Tensor, near: float = 0.0) -> torch.Tensor:
    """:func:`distortion_loss` on validated, contiguous float32 samples given by ``ray_offsets``
    [n_rays + 1] int32 (as ``render_rays(..., return_samples=True)`` returns them), skipping the
    search for each ray's first sample, ``near`` a float ≥ 0 as there. Returns [n_rays] float32."""
    return _Distortion.apply(weights, t_starts, t_ends, ray_offsets, float(near))


def distortion_loss(weights: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor,
                    ray_indices: torch.Tensor, n_rays: int, near: float = 0.0) -> torch.Tensor:
    """Mip-NeRF 360's distortion loss of every ray: small when a ray's weight sits in one
    short stretch (a crisp surface), large when it is spread along the ray.

    .. math::
        L_r = \\sum_{i,j} w_i w_j \\left|m_i - m_j\\right| + \\tfrac13 \\sum_i w_i^2 \\delta_i,
        \\qquad m_i = \\tfrac12 (t^{start}_i + t^{end}_i), \\quad \\delta_i = t^{end}_i - t^{start}_i

    (in the units of ``t``), computed in O(samples) with prefix sums. With ``near`` > 0 the
    intervals are first mapped to mip-NeRF 360's normalised distance :math:`s = 1 - near / t`
    (distances below ``near`` count as ``near``), which weighs a stretch near the camera more
    than one far behind the surface.

    Args:
        weights: [S] float32 compositing weights :math:`w_i` (differentiable, e.g. from
            :func:`ngp_warp.composite` with ``return_weights``).
        t_starts, t_ends: [S] float32 sample intervals (differentiable, through the midpoints
            and lengths; with ``near`` > 0 not below ``near``, where s is clamped).
        ray_indices: [S] int64 ray of each sample, **sorted** (samples of a ray contiguous and
            front to back; not checked on the device). Rows with index ``n_rays`` or more
            (the padding rows of ``render_rays``) belong to no ray and are ignored.
        n_rays: number of rays.
        near: 0 (distances in the units of ``t``) or the rays' near distance (> 0, units of ``t``).

    Returns:
        [n_rays] float32 loss per ray (0 for rays without samples), differentiable w.r.t. ``weights``,
        ``t_starts`` and ``t_ends``.
    """
    if not isinstance(weights, torch.Tensor) or weights.dim() != 1:
        raise ValueError(f"weights must be a [S] tensor, got {getattr(weights, 'shape', type(weights).__name__)}")
    n = weights.shape[0]
    for name, t in (("weights", weights), ("t_starts", t_starts), ("t_ends", t_ends)):
        if not isinstance(t, torch.Tensor) or tuple(t.shape) != (n,) or t.dtype != torch.float32:
            raise ValueError(f"{name} must be [{n}] float32, got {getattr(t, 'shape', t)} "
                             f"{getattr(t, 'dtype', '')}".rstrip())
        if t.device != weights.device:
            raise ValueError(f"{name} is on {t.device} but weights on {weights.device}")
    if (not isinstance(ray_indices, torch.Tensor) or tuple(ray_indices.shape) != (n,)
            or ray_indices.dtype != torch.int64 or ray_indices.device != weights.device):
        raise ValueError(f"ray_indices must be [{n}] int64 on {weights.device}")
    if not isinstance(n_rays, int) or n_rays < 0:
        raise ValueError(f"n_rays must be a non-negative int, got {n_rays!r}")
    check_distances(near=near)
    _wp.device_of(weights)
    # offsets[r] = first sample of ray r (binary search: rows past the last ray are left out)
    offsets = torch.searchsorted(ray_indices, torch.arange(n_rays + 1, device=weights.device), out_int32=True)
    return distortion_loss_packed(weights.contiguous(), t_starts.contiguous(), t_ends.contiguous(), offsets, float(near))
