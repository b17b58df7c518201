"""The optimizer state of a field: both Adams, the weight average and the deferred update.

The MLPs step with :class:`ngp_warp.ops.optim.Adam` (torch's fused Adam); the hash table with
:class:`ngp_warp.ops.optim.LazyAdam` (entries without gradient stand still), or with the MLPs'
Adam when ``lazy_table=False``. The update of
a step is deferred: :meth:`FieldOptimizer.defer` records its learning rate and average decay,
:meth:`FieldOptimizer.flush` queues it, which the trainer does inside the next step's march
(see :meth:`ngp_warp.training.trainer.Trainer.step`) or before anything reads the weights.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable

import torch

from ngp_warp.ops.field import NGPField
from ngp_warp.ops.optim import Adam, LazyAdam

BETAS = (0.9, 0.99)
EPS = 1e-15


class FieldOptimizer:
    """Adam for the field's parameters and, when ``weight_average`` > 0, an exponential moving
    average of them (what renders use).

    Args:
        field: the field; its parameters are updated in place.
        lr: peak learning rate (see :meth:`learning_rate`).
        warmup_steps: steps of the learning rate's linear warm-up (≥ 1).
        weight_decay: on the MLP weights only.
        weight_average: the average's decay per step late in training (0: no average).
        lazy_table: the hash table gets its own :class:`LazyAdam`, which also keeps the table's
            average in its update pass; the MLPs' averages are lerped after each update.

    Attributes:
        mlp_adam: the :class:`~ngp_warp.ops.optim.Adam` of the MLPs (and of the table unless
            ``lazy_table``).
        table_adam: the table's ``LazyAdam``, or None.
        averaged: one float32 tensor per field parameter (shapes and order of
            ``field.parameters()``), or None without averaging; read it through
            :meth:`averaged_weights`.
    """

    def __init__(self, field: NGPField, lr: float, weight_decay: float, weight_average: float, lazy_table: bool,
                 warmup_steps: int = 100):
        self.lr = lr
        self.warmup_steps = warmup_steps
        self.weight_average = weight_average
        table = {"params": list(field.encoding.parameters()), "weight_decay": 0.0}
        mlp = {"params": field.mlp_parameters(), "weight_decay": weight_decay}
        self.mlp_adam = Adam([mlp] if lazy_table else [table, mlp], lr=lr, betas=BETAS, eps=EPS)
        self.table_adam = LazyAdam(table["params"], lr=lr, betas=BETAS, eps=EPS) if lazy_table else None
        self._params = list(field.parameters())
        self.averaged = [p.detach().clone() for p in self._params] if weight_average > 0 else None
        self._pending: tuple[float, float | None] | None = None  # (lr, average decay) of the deferred update
        self._in_field = 0  # averaged_in_field blocks open: the outermost swaps the weights
        self._in_field_lock = threading.Lock()  # the count is shared: a block may open from any thread
        self.before_update: Callable[[], None] | None = None  # data-parallel: wait for the reduced gradients
        # The lazy table optimizer keeps the table's average; the rest are lerped after each update.
        self._lerped: tuple[list[torch.Tensor], list[torch.Tensor]] = ([], [])
        for p, average in zip(self._params, self.averaged or []):
            if self.table_adam is not None and any(p is q for q in table["params"]):
                self.table_adam.keep_average(p, average)
            else:
                self._lerped[0].append(average)
                self._lerped[1].append(p.detach())  # shares the storage; keeps the lerp out of autograd

    def optimizers(self) -> list[Adam | LazyAdam]:
        """The MLPs' Adam (and the table's, unless the table has its own LazyAdam)."""
        return [self.mlp_adam] if self.table_adam is None else [self.mlp_adam, self.table_adam]

    def learning_rate(self, step: int, progress: float) -> float:
        """Linear warm-up over ``warmup_steps`` steps, then ×0.33 at 50 %, 75 % and 90 % of the budget
        (``progress`` in [0, 1])."""
        warm = min(1.0, 0.01 + step / self.warmup_steps)
        return self.lr * (warm * 0.33 ** sum(progress >= m for m in (0.5, 0.75, 0.9)))

    def average_decay(self, step: int) -> float | None:
        """The weight average's decay at ``step`` (None without averaging): a short memory
        early on, so the random initial weights wash out quickly."""
        if self.averaged is None:
            return None
        return min(self.weight_average, (1 + step) / (10 + step))

    def zero_grad(self) -> None:
        """Drop the gradients (zero_grad(set_to_none=True) at a 20th of its host time)."""
        for p in self._params:
            p.grad = None

    def defer(self, step: int, progress: float) -> None:
        """Record the update of the gradients in hand with the schedules at ``step`` and
        ``progress``; :meth:`flush` queues it."""
        self._pending = (self.learning_rate(step, progress), self.average_decay(step))

    @property
    def pending(self) -> bool:
        """Whether an update waits for :meth:`flush`."""
        return self._pending is not None

    def flush(self) -> None:
        """Queue the deferred update, if any: every Adam at its learning rate, then the average
        at its decay."""
        if self._pending is None:
            return
        lr, decay = self._pending
        self._pending = None
        if self.before_update is not None:
            self.before_update()
        for opt in self.optimizers():
            for group in opt.param_groups:
                group["lr"] = lr
        if self.table_adam is not None:
            self.table_adam.param_groups[0]["average_decay"] = decay
        for opt in self.optimizers():
            opt.step()
        if self._lerped[0]:
            torch._foreach_lerp_(self._lerped[0], self._lerped[1], 1.0 - decay)

    def averaged_weights(self) -> list[torch.Tensor] | None:
        """:attr:`averaged` up to date, the deferred update applied first (None without
        averaging)."""
        self.flush()
        if self.averaged is not None and self.table_adam is not None:
            self.table_adam.flush_averages()
        return self.averaged

    @contextlib.contextmanager
    def averaged_in_field(self):
        """The averaged weights in the field inside the block (when averaging is on), the live
        ones restored after it; either way the deferred update is applied first. A block opened
        inside another (from any thread; e.g. each render inside an evaluation's or a video's)
        changes nothing: the outermost swaps the weights once."""
        with self._in_field_lock:
            outermost = self._in_field == 0
            self._in_field += 1
        try:
            averaged = self.averaged_weights() if outermost else None
            if averaged is None:
                yield
                return
            params = [p.data for p in self._params]
            live = [p.clone() for p in params]
            torch._foreach_copy_(params, averaged)
            try:
                yield
            finally:
                torch._foreach_copy_(params, live)
        finally:
            with self._in_field_lock:
                self._in_field -= 1

    def state_dict(self) -> dict:
        """``optimizer`` (the MLPs' Adam), ``table_optimizer`` (LazyAdam's, or None) and
        ``averaged`` (the average, or None): the keys of format-v1 checkpoints. Applies the
        deferred update first, so that the state matches the field's weights."""
        averaged = self.averaged_weights()
        return {"optimizer": self.mlp_adam.state_dict(),
                "table_optimizer": None if self.table_adam is None else self.table_adam.state_dict(),
                "averaged": averaged}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`'s keys (other keys are ignored) into an optimizer built
        with the same settings, after the field's weights: a state without ``averaged``
        (written before weight averaging) starts the average from the weights."""
        self._pending = None
        self.mlp_adam.load_state_dict(state["optimizer"])
        if self.table_adam is not None:
            self.table_adam.load_state_dict(state["table_optimizer"])
        if self.averaged is not None:
            saved = state.get("averaged") or [p.detach() for p in self._params]
            torch._foreach_copy_(self.averaged, [t.to(a.device) for t, a in zip(saved, self.averaged, strict=True)])
