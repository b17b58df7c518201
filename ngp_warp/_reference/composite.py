"""Float64 pure-torch twin of :func:`ngp_warp.composite` (per-ray loops; tests only)."""

from __future__ import annotations

import torch

f64 = torch.float64


def ray_offsets_from_indices(ray_indices: torch.Tensor, n_rays: int) -> torch.Tensor:
    """[S] sorted ray indices → [n_rays + 1] int64 offsets."""
    return torch.searchsorted(ray_indices.long(), torch.arange(n_rays + 1, device=ray_indices.device))


def ray_terms(sigmas, t_starts, t_ends, early_stop_eps):
    """Per-sample δ, α, T, T_next and the contribution mask of one ray (float64)."""
    delta = (t_ends - t_starts).to(f64)
    x = sigmas.to(f64) * delta
    alpha = -torch.expm1(-x)
    tau = torch.cumsum(x, 0)
    trans = torch.exp(-(tau - x))
    keep = (trans >= early_stop_eps).to(f64)
    return delta, alpha, trans, torch.exp(-tau), keep


def composite(sigmas, rgbs, t_starts, t_ends, ray_indices, n_rays: int, early_stop_eps: float = 0.0):
    """Float64 loop over rays; differentiable by autograd. Returns rgb, opacity, depth, weights."""
    offsets = ray_offsets_from_indices(ray_indices, n_rays).tolist()
    rgb, opacity, depth, weights = [], [], [], []
    for r in range(n_rays):
        s = slice(offsets[r], offsets[r + 1])
        _, alpha, trans, _, keep = ray_terms(sigmas[s], t_starts[s], t_ends[s], early_stop_eps)
        w = trans * alpha * keep
        mid = 0.5 * (t_starts[s] + t_ends[s]).to(f64)
        rgb.append((w[:, None] * rgbs[s].to(f64)).sum(0))
        opacity.append(w.sum())
        depth.append((w * mid).sum())
        weights.append(w)
    z = torch.zeros(0, dtype=f64, device=sigmas.device)
    return (
        torch.stack(rgb) if rgb else z.reshape(0, 3),
        torch.stack(opacity) if opacity else z,
        torch.stack(depth) if depth else z,
        torch.cat(weights) if weights else z,
    )


def composite_backward(sigmas, rgbs, t_starts, t_ends, ray_indices, n_rays, g_rgb, g_opacity, g_depth,
                           g_weights=None, early_stop_eps: float = 0.0):
    """Twin of the backward kernel: with v_i = c_i·g_C + m_i g_D + g_O + g_w_i and
    G_i = T_{i+1} v_i − Σ_{j>i} w_j v_j, dL/dc_i = w_i g_C, dL/dσ_i = δ_i G_i and
    dL/dt_start_i, dL/dt_end_i = ∓σ_i G_i + w_i g_D / 2."""
    offsets = ray_offsets_from_indices(ray_indices, n_rays).tolist()
    g_sigmas, g_rgbs, g_starts, g_ends = [], [], [], []
    for r in range(n_rays):
        s = slice(offsets[r], offsets[r + 1])
        delta, alpha, trans, trans_next, keep = ray_terms(sigmas[s], t_starts[s], t_ends[s], early_stop_eps)
        w = trans * alpha * keep
        mid = 0.5 * (t_starts[s] + t_ends[s]).to(f64)
        v = rgbs[s].to(f64) @ g_rgb[r].to(f64) + mid * g_depth[r].to(f64) + g_opacity[r].to(f64)
        if g_weights is not None:
            v = v + g_weights[s].to(f64)
        wv = w * v
        suffix = torch.flip(torch.cumsum(torch.flip(wv, [0]), 0), [0]) - wv
        big_g = trans_next * keep * v - suffix
        g_sigmas.append(delta * big_g)
        g_rgbs.append(w[:, None] * g_rgb[r].to(f64))
        along, middle = sigmas[s].to(f64) * big_g, 0.5 * w * g_depth[r].to(f64)
        g_starts.append(middle - along)
        g_ends.append(middle + along)
    return torch.cat(g_sigmas), torch.cat(g_rgbs), torch.cat(g_starts), torch.cat(g_ends)
