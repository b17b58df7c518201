"""Float64 pure-torch twin of :func:`ngp_warp.prune_samples`'s selection (tests only)."""

from __future__ import annotations

import torch

from ngp_warp._reference.composite import ray_offsets_from_indices, ray_terms


def prune_samples(sigmas, t_starts, t_ends, ray_indices, n_rays: int, early_stop_eps: float):
    """[S] bool: the samples that composite (transmittance in front ≥ eps) and [S] float64 T."""
    offsets = ray_offsets_from_indices(ray_indices, n_rays).tolist()
    keep, trans = [], []
    for r in range(n_rays):
        s = slice(offsets[r], offsets[r + 1])
        _, _, t, _, k = ray_terms(sigmas[s], t_starts[s], t_ends[s], early_stop_eps)
        keep.append(k.bool())
        trans.append(t)
    return torch.cat(keep), torch.cat(trans)
