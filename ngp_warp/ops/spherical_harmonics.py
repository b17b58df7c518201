"""Real spherical harmonics of degree 4 of unit view directions (the field's colour input): a
Warp forward and a hand-written Warp backward, so that a loss reaches the directions (a render's
``rays_d``)."""

from __future__ import annotations

import torch
import warp as wp

from ngp_warp import _wp
from ngp_warp.ops._differentiable_once import refuse_second_derivative
from ngp_warp.kernels import spherical_harmonics as K


class _SphericalHarmonics(torch.autograd.Function):
    """[N, 3] float32 contiguous directions → [N, 16] float32 values."""

    @staticmethod
    def forward(ctx, d: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(d)
        return _values(d)

    @staticmethod
    def backward(ctx, grad_values: torch.Tensor):
        (d,) = ctx.saved_tensors
        grad = torch.empty_like(d)
        _wp.launch(K.sh_deg4_backward, d.shape[0],
                   [_wp.to_wp(d, dtype=wp.vec3), grad_values.detach().float().contiguous().view(-1),
                    _wp.to_wp(grad, dtype=wp.vec3)], _wp.device_of(d))
        return refuse_second_derivative("spherical_harmonics_deg4", (grad,), (d, grad_values))[0]


def _values(d: torch.Tensor) -> torch.Tensor:
    out = torch.empty(d.shape[0], 16, device=d.device, dtype=torch.float32)
    _wp.launch(K.sh_deg4, 4 * d.shape[0], [_wp.to_wp(d.detach(), dtype=wp.vec3),
                                           _wp.to_wp(out.view(-1, 4), dtype=wp.vec4)], _wp.device_of(d))
    return out


def spherical_harmonics_deg4(d: torch.Tensor) -> torch.Tensor:
    """Real spherical harmonics of degree 4 (bands 0..3, 16 values) of unit directions, in Warp,
    with tiny-cuda-nn's ordering and signs.

    d: [N, 3] float unit vectors (CPU or CUDA; any strides, computed in float32). Returns [N, 16]
    float32, differentiable in ``d`` once (a second derivative raises).
    """
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"directions must be [N, 3], got {tuple(d.shape)}")
    d32 = d.float().contiguous()
    if d32.requires_grad and torch.is_grad_enabled():
        return _SphericalHarmonics.apply(d32)
    return _values(d32)
