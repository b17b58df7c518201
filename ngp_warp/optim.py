"""``LazyAdam``: Adam that skips entries with a zero gradient, for hash-grid tables."""

from __future__ import annotations

import math

import torch

from ngp_warp import _wp
from ngp_warp.kernels import adam as K


class LazyAdam(torch.optim.Optimizer):
    """Adam (torch's update and bias correction) that leaves every entry whose gradient is
    exactly zero in a step as it is, value and moments, as tiny-cuda-nn does for encodings.

    For a hash table, where a batch touches a small part of the fine levels, plain Adam keeps
    moving the untouched entries along their stale first moment. The step counter (bias
    correction) is per tensor, as in ``torch.optim.SparseAdam``.

    .. math::

        g_i \\neq 0:\\quad m_i \\leftarrow \\beta_1 m_i + (1-\\beta_1) g_i,\\quad
        v_i \\leftarrow \\beta_2 v_i + (1-\\beta_2) g_i^2,\\quad
        p_i \\leftarrow p_i - \\frac{\\mathrm{lr}}{1-\\beta_1^t}
            \\frac{m_i}{\\sqrt{v_i / (1-\\beta_2^t)} + \\epsilon}

    Args:
        params: float32 contiguous tensors (CPU or CUDA) with dense gradients.
        lr, betas, eps: as ``torch.optim.Adam``.
        weight_decay: decoupled (AdamW) decay, applied to touched entries only:
            :math:`p_i \\leftarrow p_i (1 - \\mathrm{lr}\\,\\lambda)` before the Adam step.
    """

    def __init__(self, params, lr: float = 1e-2, betas: tuple[float, float] = (0.9, 0.99), eps: float = 1e-15,
                 weight_decay: float = 0.0):
        if not lr >= 0.0:
            raise ValueError(f"lr must be ≥ 0, got {lr}")
        if not all(0.0 <= b < 1.0 for b in betas) or len(betas) != 2:
            raise ValueError(f"betas must be two numbers in [0, 1), got {betas}")
        if not eps >= 0.0:
            raise ValueError(f"eps must be ≥ 0, got {eps}")
        if not weight_decay >= 0.0:
            raise ValueError(f"weight_decay must be ≥ 0, got {weight_decay}")
        super().__init__(params, {"lr": lr, "betas": tuple(betas), "eps": eps, "weight_decay": weight_decay})
        for group in self.param_groups:
            for p in group["params"]:
                if p.dtype != torch.float32 or not p.is_contiguous():
                    raise ValueError(f"LazyAdam takes contiguous float32 tensors, got {p.dtype} {tuple(p.shape)}")

    @torch.no_grad()
    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                grad = p.grad
                if grad.is_sparse or grad.dtype != torch.float32 or not grad.is_contiguous():
                    raise ValueError("LazyAdam needs dense contiguous float32 gradients")
                state = self.state[p]
                if not state:
                    state["step"] = 0
                    state["exp_avg"] = torch.zeros_like(p)
                    state["exp_avg_sq"] = torch.zeros_like(p)
                state["step"] += 1
                bc1 = 1.0 - beta1 ** state["step"]
                bc2 = math.sqrt(1.0 - beta2 ** state["step"])
                _wp.launch(
                    K.lazy_adam_step, p.numel(),
                    [p.view(-1), grad.view(-1), state["exp_avg"].view(-1), state["exp_avg_sq"].view(-1),
                     group["lr"] * bc2 / bc1, beta1, beta2, group["eps"] * bc2,
                     group["lr"] * group["weight_decay"]],
                    _wp.device_of(p),
                )
        return loss
