"""The field's optimizers: ``Adam`` (torch's fused update) and ``LazyAdam`` (Adam that skips
entries with a zero gradient, for hash-grid tables).

Neither is a ``torch.optim.Optimizer``: building one of those imports ``torch._dynamo`` (about
1.5 s of a CPU start-up, more where Python compiles from source), and its ``step`` runs hooks
and a dynamo graph break (about 0.1 ms of host time a step on the CPU). Their state dicts keep
``torch.optim``'s format, so a state saved by ``torch.optim.Adam`` over the same parameters loads.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Iterable

import torch

from ngp_warp import _wp
from ngp_warp.kernels import optim as K


_REBASE_LOG_DECAY = -64.0  # flush and rebase a kept average's log-decays beyond this


class _Optimizer:
    """Parameter groups (``param_groups``: dicts with ``params`` and the group's settings) and
    per-parameter ``state``, saved and loaded in ``torch.optim``'s state_dict format."""

    def __init__(self, params: Iterable, defaults: dict):
        groups = list(params)
        if not groups:
            raise ValueError("the optimizer got no parameters")
        if not isinstance(groups[0], dict):
            groups = [{"params": groups}]
        self.param_groups = [{**defaults, **g, "params": list(g["params"])} for g in groups]
        self.state: dict[torch.Tensor, dict] = collections.defaultdict(dict)

    def _cast_state(self, key: str, value, param: torch.Tensor):
        """A loaded state entry as this optimizer keeps it: tensors on the parameter's device and
        in its dtype."""
        return value.to(param.device, param.dtype) if isinstance(value, torch.Tensor) else value

    def zero_grad(self, set_to_none: bool = True) -> None:
        for group in self.param_groups:
            for p in group["params"]:
                if set_to_none:
                    p.grad = None
                elif p.grad is not None:
                    p.grad.zero_()

    def state_dict(self) -> dict:
        """``{"state": {index: entries}, "param_groups": [settings with "params": indices]}``,
        parameters numbered in group order (torch.optim's format; the state's tensors are
        this optimizer's own, not copies)."""
        index: dict[int, int] = {}
        groups = []
        for group in self.param_groups:
            ids = [index.setdefault(id(p), len(index)) for p in group["params"]]
            groups.append({**{k: v for k, v in group.items() if k != "params"}, "params": ids})
        return {"state": {index[id(p)]: dict(s) for p, s in self.state.items()}, "param_groups": groups}

    def load_state_dict(self, saved: dict) -> None:
        """Restore :meth:`state_dict`'s state and the settings this optimizer's groups have; the
        groups and their sizes must match."""
        groups = saved["param_groups"]
        if len(groups) != len(self.param_groups) or any(
                len(g["params"]) != len(mine["params"]) for g, mine in zip(groups, self.param_groups)):
            raise ValueError("the saved optimizer state has other parameter groups than this optimizer")
        self.state = collections.defaultdict(dict)
        for g, mine in zip(groups, self.param_groups):
            mine.update({k: v for k, v in g.items() if k != "params" and k in mine})
            for i, p in zip(g["params"], mine["params"]):
                if i in saved["state"]:
                    self.state[p] = {k: self._cast_state(k, v, p) for k, v in saved["state"][i].items()}


class Adam(_Optimizer):
    """``torch.optim.Adam`` (L2 weight decay added to the gradient, bias correction per tensor)
    as torch's fused kernel: one launch per group a step (two with the step counters), no hooks.

    Args:
        params: floating-point tensors on one device, or groups (dicts with ``params`` and any of
            the settings below); parameters without a gradient are skipped in a step.
        lr, betas, eps, weight_decay: as ``torch.optim.Adam``.
    """

    def __init__(self, params, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8,
                 weight_decay: float = 0.0):
        _check_adam_settings(lr, betas, eps, weight_decay)
        super().__init__(params, {"lr": lr, "betas": tuple(betas), "eps": eps, "weight_decay": weight_decay})
        tensors = [p for group in self.param_groups for p in group["params"]]
        if any(not p.is_floating_point() or p.device != tensors[0].device for p in tensors):
            raise ValueError("Adam takes floating-point tensors on one device")

    def _cast_state(self, key: str, value, param: torch.Tensor):
        if key == "step":  # the fused kernel reads it on the parameter's device, in float32
            return torch.as_tensor(value, dtype=torch.float32).to(param.device)
        return super()._cast_state(key, value, param)

    @torch.no_grad()
    def step(self) -> None:
        for group in self.param_groups:
            params = [p for p in group["params"] if p.grad is not None]
            if not params:
                continue
            states = []
            for p in params:
                if p not in self.state:
                    self.state[p] = {"step": torch.zeros((), dtype=torch.float32, device=p.device),
                                     "exp_avg": torch.zeros_like(p), "exp_avg_sq": torch.zeros_like(p)}
                states.append(self.state[p])
            steps = [s["step"] for s in states]
            torch._foreach_add_(steps, 1.0)
            beta1, beta2 = group["betas"]
            torch._fused_adam_(params, [p.grad for p in params], [s["exp_avg"] for s in states],
                               [s["exp_avg_sq"] for s in states], [], steps, lr=group["lr"], beta1=beta1,
                               beta2=beta2, weight_decay=group["weight_decay"], eps=group["eps"], amsgrad=False,
                               maximize=False)


def _check_adam_settings(lr: float, betas, eps: float, weight_decay: float) -> None:
    if not lr >= 0.0:
        raise ValueError(f"lr must be ≥ 0, got {lr}")
    if len(betas) != 2 or not all(0.0 <= b < 1.0 for b in betas):
        raise ValueError(f"betas must be two numbers in [0, 1), got {betas}")
    if not eps >= 0.0:
        raise ValueError(f"eps must be ≥ 0, got {eps}")
    if not weight_decay >= 0.0:
        raise ValueError(f"weight_decay must be ≥ 0, got {weight_decay}")


class LazyAdam(_Optimizer):
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
        _check_adam_settings(lr, betas, eps, weight_decay)
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
    def step(self) -> None:
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
