"""Data-parallel training on torch.distributed: NCCL between GPUs, gloo between CPU processes.

``ngp-warp train SCENE --gpus N`` (:mod:`ngp_warp.cli.ranks`) or ``torchrun --nproc-per-node N -m
ngp_warp.cli train SCENE ...`` starts N ranks. Each holds the whole model and draws its own rays
(its own seed stream) from the shared training images; after each backward the gradients are
averaged over the ranks, so every rank applies the same update and the models stay equal:

.. math::

    g = \\frac{1}{N} \\sum_r g_r, \\qquad g_r = \\nabla_\\theta \\, \\mathrm{loss}_r

Each rank's loss is the mean over its own pixels, so with equal batches :math:`g` is the gradient
of the mean over all of them. An entry stays exactly zero where it is zero on every rank, so the
lazy table Adam still skips it. All gradients go through one flat buffer and one all-reduce,
which runs while the next step marches; the deferred optimizer update waits for it.
Occupancy-grid updates take each cell's max over the ranks. The learning-rate schedule and the
time budget follow rank 0's clock, broadcast every ``READOUT_EVERY`` steps with the progress
readout. Rank 0 alone shows progress, evaluates and writes checkpoints; a checkpoint holds no
per-rank state, so ``--resume`` works with any number of ranks.
"""

from __future__ import annotations

import datetime
import os

import torch
import torch.distributed as dist

from ngp_warp.training.rank_env import started_as_rank
from ngp_warp.training.train_step import HostCopy
from ngp_warp.training.trainer import READOUT_EVERY, Trainer

FIT_MANY_TIMEOUT = datetime.timedelta(days=30)  # no store or group operation of fit-many expires during a long scene


def rank_and_size() -> tuple[int, int]:
    """(this process's rank, number of ranks): (0, 1) outside a process group."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def is_main_rank() -> bool:
    """Whether this process shows progress and writes outputs (rank 0, or the only process)."""
    return rank_and_size()[0] == 0


def join(device: str, backend: str | None = None, timeout: datetime.timedelta | None = None) -> str:
    """Join the process group of the ranks (``env://``: torchrun's or ``--gpus``'s) and return this rank's device:
    ``cuda:LOCAL_RANK`` for a CUDA ``device`` (``auto``: CUDA when present), else ``cpu``.
    ``backend`` defaults to NCCL on CUDA and gloo on the CPU."""
    from ngp_warp.training.config import default_device

    device = default_device() if device in (None, "auto") else device
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    if device.startswith("cuda"):
        device = f"cuda:{local_rank}"
        torch.cuda.set_device(local_rank)
    if not dist.is_initialized():
        backend = backend or ("nccl" if device.startswith("cuda") else "gloo")
        dist.init_process_group(backend, timeout=timeout)
    return device


def leave() -> None:
    """Leave the process group, if this process joined one."""
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


def join_data_parallel(args) -> bool:
    """``train`` as one of several ranks: join the group, put this rank's device
    in ``args.device`` and return True; otherwise False."""
    if not started_as_rank():
        return False
    args.device = join(args.device)
    return True


class GradientReducer:
    """Averages the field's gradients over the ranks: after each backward every gradient (the
    MLPs', the appearance codes' and the hash table's) is copied into one flat float32 buffer
    and reduced by one all-reduce (NCCL's average; a sum scaled by 1/N on gloo), which runs
    while the next step marches.

    :meth:`finish` (after every backward, on every rank, also without one) launches it, with
    zero gradients where a parameter got none; :meth:`wait` (before the optimizer reads them)
    waits for it and copies the averages back into ``p.grad``.
    """

    def __init__(self, field: torch.nn.Module):
        self.world_size = dist.get_world_size()
        self.params = list(field.parameters())
        self._flat = torch.empty(sum(p.numel() for p in self.params), dtype=torch.float32,
                                 device=self.params[0].device)
        self._views = [v.view_as(p) for v, p in zip(self._flat.split([p.numel() for p in self.params]), self.params)]
        self._average = dist.get_backend() == dist.Backend.NCCL  # gloo has no average
        self._in_flight: dist.Work | None = None

    def finish(self) -> None:
        """Launch the reduction of this step's gradients (zeros where a parameter got none)."""
        for p in self.params:
            if p.grad is None:
                p.grad = torch.zeros_like(p)
        torch.cat([p.grad.reshape(-1) for p in self.params], out=self._flat)
        if not self._average:
            self._flat.mul_(1.0 / self.world_size)
        op = dist.ReduceOp.AVG if self._average else dist.ReduceOp.SUM
        self._in_flight = dist.all_reduce(self._flat, op=op, async_op=True)

    def wait(self) -> None:
        """Wait for the launched reduction; the averaged gradients are then in ``p.grad``."""
        if self._in_flight is None:
            return
        self._in_flight.wait()
        self._in_flight = None
        torch._foreach_copy_([p.grad for p in self.params], self._views)


class RankZeroClock:
    """Rank 0's training seconds, broadcast every ``READOUT_EVERY`` steps (only when the budget
    is in seconds) and read at the next such step, when the broadcast has landed (no wait for the
    GPU): every rank sees the same learning-rate schedule and stops at the same step."""

    def __init__(self, trainer: Trainer):
        self.trainer = trainer
        self._seconds = torch.zeros(1, dtype=torch.float64, device=trainer.device)
        self._copy = HostCopy(1, trainer.device)
        self._agreed = trainer.train_seconds

    def __call__(self, step: int) -> float:
        """The training seconds all ranks agree on at ``step``: rank 0's of ``READOUT_EVERY``
        steps before (its start's before the first broadcast has been read)."""
        if self.trainer.config.seconds is not None and step % READOUT_EVERY == 0:
            if self._copy.pending:
                self._agreed = self._copy.read()[0]
            self._seconds.fill_(self.trainer.train_seconds)
            dist.broadcast(self._seconds, src=0)
            self._copy.start(self._seconds)
        return self._agreed


def broadcast_state(trainer: Trainer) -> None:
    """Copy rank 0's field, grid and weight average to every rank."""
    tensors = list(trainer.field.state_dict().values()) + list(trainer.grid.state_dict().values())
    tensors += trainer.weights.averaged or []
    for t in tensors:
        dist.broadcast(t.data, src=0)


def all_reduce_max(values: torch.Tensor) -> None:
    """Each element's max over the ranks, in place."""
    dist.all_reduce(values, op=dist.ReduceOp.MAX)


def make_data_parallel(trainer: Trainer) -> GradientReducer:
    """Turn ``trainer`` into this rank's part of data-parallel training (a process group must be
    initialized): rank 0's state on every rank, this rank's ray stream, the gradient reduction
    after each backward (waited before each optimizer update), the grid updates' max over the
    ranks and rank 0's clock. Returns the reducer. ValueError (one line) for a trainer with
    camera refinement, whose pose corrections the reduction does not share."""
    if trainer.cameras is not None:
        raise ValueError("camera_refinement is not supported with data-parallel training (--gpus > 1)")
    rank, _ = rank_and_size()
    broadcast_state(trainer)
    reducer = GradientReducer(trainer.field)
    trainer.ray_stream = rank
    trainer.gradient_reduction = reducer.finish
    trainer.weights.before_update = reducer.wait
    trainer.grid.merge_samples = all_reduce_max
    trainer.shared_clock = RankZeroClock(trainer)
    return reducer
