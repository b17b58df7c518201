"""Float64 pure-torch twin of :class:`ngp_warp.ops.optim.LazyAdam` (tests only)."""

from __future__ import annotations

import torch


def lazy_adam(param, grads, lr: float, betas=(0.9, 0.99), eps: float = 1e-15,
                  weight_decay: float = 0.0, average_decays=None):
    """``param`` after one LazyAdam step per gradient in ``grads`` (all float64). With
    ``average_decays`` (one per step), also the moving average of ``param`` updated densely
    after every step: returns (param, average)."""
    p = param.double().clone()
    average = p.clone()
    m, v = torch.zeros_like(p), torch.zeros_like(p)
    b1, b2 = betas
    for t, g in enumerate(grads, start=1):
        g = g.double()
        hit = g != 0
        m = torch.where(hit, b1 * m + (1 - b1) * g, m)
        v = torch.where(hit, b2 * v + (1 - b2) * g * g, v)
        step = lr / (1 - b1**t) * m / ((v / (1 - b2**t)).sqrt() + eps)
        p = torch.where(hit, p * (1 - lr * weight_decay) - step, p)
        if average_decays is not None:
            average = torch.lerp(average, p, 1 - average_decays[t - 1])
    return p if average_decays is None else (p, average)
