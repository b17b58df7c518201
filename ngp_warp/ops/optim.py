"""``LazyAdam``: Adam that skips entries with a zero gradient, for hash-grid tables."""

from __future__ import annotations

import math

import torch

from ngp_warp import _wp
from ngp_warp.kernels import optim as K


_REBASE_LOG_DECAY = -64.0  # flush and rebase a kept average's log-decays beyond this


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

    With :meth:`keep_average`, the same pass keeps an exponential moving average of a tensor,
    equal to updating every entry's average every step,

    .. math::

        a_i \\leftarrow a_i + (1 - d_t)\\,(p_i - a_i),

    while touching only the entries with a gradient (an untouched entry's weight stands still, so
    its average catches up in closed form when next touched, or at :meth:`flush_averages`). The
    decay :math:`d_t` of a step is the group's ``average_decay``, set before each step.

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
        super().__init__(params, {"lr": lr, "betas": tuple(betas), "eps": eps, "weight_decay": weight_decay,
                                  "average_decay": None})
        self._averages: dict[torch.Tensor, torch.Tensor] = {}
        for group in self.param_groups:
            for p in group["params"]:
                if p.dtype != torch.float32 or not p.is_contiguous():
                    raise ValueError(f"LazyAdam takes contiguous float32 tensors, got {p.dtype} {tuple(p.shape)}")

    def keep_average(self, param: torch.Tensor, average: torch.Tensor) -> None:
        """Keep ``average`` (a tensor like ``param``, the caller's; it holds the average's
        start) as the moving average of ``param`` from the next step on. Call
        :meth:`flush_averages` before reading it. The averages are not in :meth:`state_dict`:
        the caller saves them (flushed) and restores them after :meth:`load_state_dict`."""
        if not any(param is p for group in self.param_groups for p in group["params"]):
            raise ValueError("keep_average: not a parameter of this optimizer")
        if average.shape != param.shape or average.dtype != torch.float32 or not average.is_contiguous() \
                or average.device != param.device:
            raise ValueError(f"keep_average: the average must be a contiguous float32 tensor like the "
                             f"parameter {tuple(param.shape)} on {param.device}")
        self._averages[param] = average
        state = self.state[param]
        state["log_decay"] = 0.0  # L: the sum of log d since the last flush
        state["synced"] = torch.zeros_like(param)  # L at each entry's last catch-up

    def load_state_dict(self, state_dict: dict) -> None:
        super().load_state_dict(state_dict)
        for group in self.param_groups:  # groups saved before averages existed
            group.setdefault("average_decay", None)
        for p in self._averages:  # state saved before the average was kept
            state = self.state[p]
            if "synced" not in state:
                state["log_decay"] = 0.0
                state["synced"] = torch.zeros_like(p)

    @torch.no_grad()
    def flush_averages(self) -> None:
        """Bring every kept average up to date (one pass over each)."""
        for p in self._averages:
            self._flush(p)

    def _flush(self, p: torch.Tensor) -> None:
        state = self.state[p]
        _wp.launch(K.flush_average, p.numel(),
                   [p.view(-1), self._averages[p].view(-1), state["synced"].view(-1), state["log_decay"]],
                   _wp.device_of(p))
        state["log_decay"] = 0.0  # the kernel rebased every entry's synced to 0

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
                average = self._averages.get(p)
                decay = group.get("average_decay")
                if average is not None and (decay is None or not 0.0 < decay < 1.0):
                    raise ValueError(f"LazyAdam keeps an average: set the group's average_decay in (0, 1), got {decay}")
                if "step" not in state:
                    state["step"] = 0
                    state["exp_avg"] = torch.zeros_like(p)
                    state["exp_avg_sq"] = torch.zeros_like(p)
                state["step"] += 1
                bc1 = 1.0 - beta1 ** state["step"]
                bc2 = math.sqrt(1.0 - beta2 ** state["step"])
                adam = [p.view(-1), grad.view(-1), state["exp_avg"].view(-1), state["exp_avg_sq"].view(-1),
                        group["lr"] * bc2 / bc1, beta1, beta2, group["eps"] * bc2, group["lr"] * group["weight_decay"]]
                averaging = [0, None, None, 0.0, 0.0, 0.0]
                if average is not None:
                    if state["log_decay"] < _REBASE_LOG_DECAY:  # keep float32 L small (about 1e-5 relative)
                        self._flush(p)
                    before = state["log_decay"]
                    state["log_decay"] = before + math.log(decay)
                    averaging = [1, average.view(-1), state["synced"].view(-1), before, state["log_decay"], decay]
                _wp.launch(K.lazy_adam_step, p.numel(), adam + averaging, _wp.device_of(p))
        return loss
