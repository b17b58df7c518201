"""Pruning marched samples to those that composite, before the field's gradient pass.

Ray marching keeps every sample in an occupied cell, including those behind a surface, where the
transmittance is already below the early-stop threshold. Those samples cost a full forward and
backward pass of the field and contribute nothing. As in instant-ngp and nerfacc's ``sigma_fn``,
a cheap no-grad density pass finds the samples that composite,

.. math::

    T_i = \\prod_{j<i} e^{-\\sigma_j \\delta_j} \\ge \\epsilon,

and only those go on to the field with gradients. With a ``capacity`` the kept samples are
packed into a buffer of exactly that many rows (no host synchronisation, fixed shapes); rays
that do not fit whole are dropped and flagged.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import warp as wp

from ngp_warp import _wp
from ngp_warp.kernels import prune as K
from ngp_warp.ops.raymarch import RaySamples

_BLOCK = 32  # one thread walks a whole ray


@dataclass
class PrunedSamples:
    """Attributes:
        samples: the kept samples (sorted by ray, front to back); with a capacity, then padding
            rows up to it: ray index ``n_rays``, empty interval ``[0, 0]``, at ``pad_position``.
        ray_mask: [n_rays] bool, rays whose contributing samples were all kept (False: dropped
            for lack of room; such rays have no samples). Padding rows carry weight 0 in
            :func:`ngp_warp.render_rays`; their ray index ``n_rays`` is out of range, so index
            per-ray tensors with the kept rows only (``ray_offsets[-1]`` of them).
        n_contributing: [1] int32 on the device, contributing samples of all rays (before the
            capacity cut).
    """

    samples: RaySamples
    ray_mask: torch.Tensor
    n_contributing: torch.Tensor


@torch.no_grad()
def prune_samples(
    samples: RaySamples,
    sigmas: torch.Tensor,
    early_stop_eps: float = 1e-4,
    capacity: int | None = None,
    pad_position: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> PrunedSamples:
    """Keep the samples that composite with densities ``sigmas``.

    Args:
        samples: :class:`ngp_warp.RaySamples` from :func:`ngp_warp.ray_marching`, S samples.
        sigmas: [S] float32 densities of the samples (from a no-grad pass).
        early_stop_eps: a sample composites while the transmittance in front of it is
            ``≥ early_stop_eps`` (as in :func:`ngp_warp.composite`; 0 keeps every sample).
        capacity: None sizes the output to the kept samples (one host synchronisation); an int
            gives exactly ``capacity`` rows (padded, rays that do not fit dropped), no sync.
        pad_position: where padding rows sit; choose a point inside your field's box.

    Returns:
        :class:`PrunedSamples`.
    """
    n_samples = samples.n_samples
    if not isinstance(sigmas, torch.Tensor) or tuple(sigmas.shape) != (n_samples,):
        raise ValueError(f"sigmas must be [{n_samples}], got {getattr(sigmas, 'shape', type(sigmas).__name__)}")
    if sigmas.dtype != torch.float32 or sigmas.device != samples.t_starts.device:
        raise ValueError(f"sigmas must be float32 on {samples.t_starts.device}, got {sigmas.dtype} on {sigmas.device}")
    if early_stop_eps < 0:
        raise ValueError(f"early_stop_eps must be ≥ 0, got {early_stop_eps}")
    if capacity is not None and capacity < 1:
        raise ValueError(f"capacity must be ≥ 1, got {capacity}")
    offsets = samples.ray_offsets
    n_rays, dev = offsets.shape[0] - 1, offsets.device
    device = _wp.device_of(offsets)
    counts = torch.empty(n_rays, dtype=torch.int32, device=dev)
    _wp.launch(K.count_contributing, n_rays, [sigmas.contiguous(), samples.t_starts, samples.t_ends, offsets,
                                              float(early_stop_eps), counts], device, block_dim=_BLOCK)
    inclusive = torch.cumsum(counts, 0, dtype=torch.int32)
    n_contributing = inclusive[-1:] if n_rays else counts.new_zeros(1)
    if capacity is None:
        capacity = int(n_contributing)  # the host synchronisation that sizes the output
    new_offsets = torch.empty(n_rays + 1, dtype=torch.int32, device=dev)
    ray_mask = torch.empty(n_rays, dtype=torch.bool, device=dev)
    _wp.launch(K.fit_rays, n_rays + 1, [n_rays, capacity, inclusive, new_offsets, ray_mask.view(torch.uint8)], device)
    ray_indices = torch.empty(capacity, dtype=torch.int64, device=dev)
    floats = torch.empty(8 * capacity, dtype=torch.float32, device=dev)
    t_starts, t_ends = floats[:capacity], floats[capacity : 2 * capacity]
    positions = floats[2 * capacity : 5 * capacity].view(capacity, 3)
    directions = floats[5 * capacity :].view(capacity, 3)
    _wp.launch(
        K.pack_contributing, max(n_samples, capacity),
        [n_samples, capacity, n_rays, samples.ray_indices, offsets, new_offsets, samples.t_starts,
         samples.t_ends, samples.positions, samples.directions, wp.vec3(*pad_position),
         ray_indices, t_starts, t_ends, positions, directions],
        device,
    )
    pruned = RaySamples(ray_indices, t_starts, t_ends, positions, directions, new_offsets)
    return PrunedSamples(pruned, ray_mask, n_contributing)
