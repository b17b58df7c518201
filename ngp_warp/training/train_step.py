"""The parts of a training step: the field as a step evaluates it (CUDA graphs), the ray-count
control, and the step's phases as replaceable calls (:class:`StepPhases`, for timers)."""

from __future__ import annotations

import contextlib
import dataclasses
import threading
from collections.abc import Callable
from dataclasses import dataclass

import torch

from ngp_warp.ops.field import NGPField
from ngp_warp.ops.graphs import GraphedDensity


class _FieldForward(torch.nn.Module):
    """The field's forward as its own module (its parameters are the field's)."""

    def __init__(self, field: NGPField):
        super().__init__()
        self.field = field

    def forward(self, positions: torch.Tensor, directions: torch.Tensor, image_indices: torch.Tensor | None = None):
        return self.field(positions, directions, image_indices)

    def parameters(self, recurse: bool = True):
        """The field's parameters that its forward uses (a graph capture differentiates each):
        all but the environment's, which the background of the loss uses instead."""
        background = [] if self.field.environment is None else list(self.field.environment.parameters())
        return (p for p in self.field.parameters(recurse) if all(p is not q for q in background))


def import_capture_modules() -> None:
    """Import the module that the backward of a CUDA-graph capture imports on its first call
    (``torch.autograd.grad`` with given output gradients imports
    ``torch.fx.experimental.symbolic_shapes``, sympy with it: about 0.45 s on a fast host with
    bytecode written, 3 s where Python compiles it), so that it counts as start-up, not as the
    first training step."""
    import torch.fx.experimental.symbolic_shapes  # noqa: F401


def uses_graphs(config, device_type: str) -> bool:
    """Whether a training step with ``config`` (a :class:`~ngp_warp.training.config.TrainConfig`)
    on a ``device_type`` device replays CUDA graphs: CUDA training with pruning and ``cuda_graph``."""
    return bool(config.cuda_graph and config.prune and device_type == "cuda")


def _import_capture_modules_quietly() -> None:
    try:
        import_capture_modules()
    except Exception:  # the graphed TrainingField imports it again, and raises it there
        pass


@contextlib.contextmanager
def capture_imports_alongside(wanted: bool):
    """Within, when ``wanted``: :func:`import_capture_modules` on a daemon thread (the command
    line loads the scene meanwhile), joined when the block ends without an error; an error leaves
    it running rather than wait for it. With the thread, start-up plus first step measured level;
    with the import in the Trainer alone, 0.53 s longer (RESULTS.md)."""
    if not wanted:
        yield
        return
    thread = threading.Thread(target=_import_capture_modules_quietly, name="capture imports", daemon=True)
    thread.start()
    yield
    thread.join()


class TrainingDiverged(RuntimeError):
    """The loss became NaN or infinite; the message is one line naming the step."""


class TrainingField:
    """The field as a training step evaluates it. With ``graphs`` (CUDA training with pruning),
    the forward and backward at exactly ``rows`` rows in training mode replay CUDA graphs (one
    launch each instead of ~70), captured on first use, and the no-gradient density pass
    replays a graph per bucket of sample counts (:class:`ngp_warp.ops.graphs.GraphedDensity`);
    otherwise both are the field's own.

    Args:
        field: the field. rows: the fixed row count of the pruned samples (``target_samples``).
        graphs: whether to capture and replay.
    """

    def __init__(self, field: NGPField, rows: int, graphs: bool):
        self.field = field
        self.rows = rows
        self.graphs = graphs
        self.graphed_forward = None  # captured on the first call at ``rows`` rows
        self.graphed_density: GraphedDensity | None = None
        if graphs:
            import_capture_modules()

    def __call__(self, positions: torch.Tensor, directions: torch.Tensor,
                 image_indices: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(positions [S, 3], directions [S, 3] float32, optional image_indices [S] int64 of the
        appearance codes) → (σ [S], rgb [S, 3]), as the field. The graphs take the indices as
        one more fixed-size input when the first call had them."""
        # camera refinement learns from the sample positions only: through the colour's view
        # directions the poses drift (the unturned cameras of its test scene, 0.6° → 1.2°)
        directions = directions.detach()
        inputs = (positions, directions) if image_indices is None else (positions, directions, image_indices)
        if self.graphs and positions.shape[0] == self.rows and self.field.training:
            if self.graphed_forward is None:
                # The capture's warm-up runs on a side stream, so autograd would warn that the
                # parameters' gradients arrive from another stream; that is expected here.
                quiet = getattr(torch.autograd.graph, "set_warn_on_accumulate_grad_stream_mismatch", None)
                if quiet is not None:
                    quiet(False)
                # Capture a wrapper: make_graphed_callables replaces the captured module's
                # forward, and the field itself must stay callable at any size.
                self.graphed_forward = torch.cuda.make_graphed_callables(
                    _FieldForward(self.field), tuple(t.detach().clone().requires_grad_(t.requires_grad)
                                                     for t in inputs))
            return self.graphed_forward(*inputs)
        return self.field(*inputs)

    def density(self, positions: torch.Tensor) -> torch.Tensor:
        """positions [S, 3] float32 → σ [S], no gradient (before pruning, and for the grid
        refresh)."""
        if not self.graphs:
            return self.field.density(positions)
        if self.graphed_density is None:
            self.graphed_density = GraphedDensity(self.field.density)
        return self.graphed_density(positions)


class RayCount:
    """The rays per batch, steered so that a batch holds about ``target_samples`` samples: each
    step scales the count by √(target / samples), the ratio clamped to [1/2, 2], rounded to a
    multiple of 128 in [256, ``max_rays``]."""

    def __init__(self, initial: int, max_rays: int, target_samples: int, device: torch.device):
        self.n_rays = initial
        self.max_rays = max_rays
        self.target_samples = target_samples
        self.fraction = 1.0  # contributing / marched samples, from the step before
        self._pin = device.type == "cuda"
        self._contributing_host: torch.Tensor | None = None  # [1] int32, the last step's count
        self._marched_before = 0

    def samples_in_use(self, out: dict) -> int:
        """The sample count of a render's output ``out`` that steers the ray count. Without
        pruning, the marched count. With it, the contributing count (before the capacity cut, so
        it may exceed it; the rays past the capacity are dropped): reading it would sync, so it
        is estimated as the marched count times the previous step's contributing fraction (read
        from a copy that has long finished: this step's march synchronised after it)."""
        if "n_marched" not in out:
            return int(out["n_samples"])
        marched = out["n_marched"]
        if self._contributing_host is None:
            self._contributing_host = torch.zeros(1, dtype=torch.int32, pin_memory=self._pin)
        elif self._marched_before > 0:  # the previous step's copy is done: this step's march synced
            self.fraction = min(1.0, int(self._contributing_host) / self._marched_before)
        self._contributing_host.copy_(out["n_contributing"], non_blocking=True)
        self._marched_before = marched
        return int(marched * self.fraction)

    def adjust(self, n_samples: int) -> None:
        """Scale the ray count after a batch of ``n_samples`` samples."""
        ratio = self.target_samples / max(n_samples, 1)
        new = self.n_rays * min(max(ratio, 0.5), 2.0) ** 0.5
        self.n_rays = int(min(max(256, round(new / 128) * 128), self.max_rays))

    def state_dict(self) -> dict:
        """``n_rays`` and ``sample_fraction`` (the keys of format-v1 checkpoints)."""
        return {"n_rays": self.n_rays, "sample_fraction": self.fraction}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`'s keys (others are ignored; a missing fraction is 1)."""
        self.n_rays = state["n_rays"]
        self.fraction = state.get("sample_fraction", 1.0)


def backward(loss: torch.Tensor) -> None:
    """``loss.backward()`` on the calling thread: handing the backward to autograd's CUDA worker
    thread and back cost 0.45 ms of host time per step (H200, 2^16 rows: 2.20 → 1.76 ms)."""
    with torch.autograd.set_multithreading_enabled(False):
        loss.backward()


@dataclass(frozen=True)
class StepPhases:
    """The calls a training step is made of, one per phase; the step calls nothing else that
    costs time. :meth:`wrapped` returns them passed through a wrapper (timers, counters).

    Nesting: ``density`` and ``field`` run inside ``render`` (and ``density`` inside
    ``grid_update`` on refresh steps); ``optimizer_update`` (the last step's deferred update)
    inside the march of ``render``, or first in a grid refresh.
    """

    sample_batch: Callable   # n rays → (rays_o, rays_d [n, 3], target, background [p, 3])
    grid_update: Callable    # (step, density_fn) → None: the occupancy grid's refresh
    render: Callable         # (rays_o, rays_d) → render dict of the batch
    density: Callable        # positions [S, 3] → σ [S], no gradient
    field: Callable          # (positions, directions[, images [S] int64]) → (σ [S], rgb [S, 3])
    optimizer_update: Callable  # () → None: queue the deferred optimizer update
    loss: Callable           # ngp_warp.losses.ray_loss
    distortion: Callable     # ngp_warp.losses.distortion_loss_packed
    backward: Callable       # loss → None

    def wrapped(self, wrap: Callable[[str, Callable], Callable]) -> StepPhases:
        """These phases with each call replaced by ``wrap(phase name, call)``."""
        return StepPhases(**{f.name: wrap(f.name, getattr(self, f.name)) for f in dataclasses.fields(self)})


class HostCopy:
    """Scalars read on the host without stalling the GPU: :meth:`start` queues their copy into
    pinned memory (CUDA) behind the work already queued; :meth:`read` returns them as floats, on
    CUDA after waiting for that copy alone (a read a few steps later finds it landed, where
    ``float(t)`` would wait for everything queued, a whole step's backward included). On the CPU
    the copy is immediate.

    Args:
        n: how many scalars one copy holds.
        device: the device of the tensors copied.
    """

    def __init__(self, n: int, device: torch.device | str):
        device = torch.device(device)
        self._stream = torch.cuda.current_stream(device) if device.type == "cuda" else None
        self._host = torch.zeros(n, dtype=torch.float64, pin_memory=self._stream is not None)
        self._landed = torch.cuda.Event() if self._stream is not None else None
        self.pending = False

    def start(self, *scalars: torch.Tensor) -> None:
        """Queue the copy of ``scalars`` ([] or [1] tensors of the device, n of them)."""
        for slot, value in zip(self._host, scalars, strict=True):
            slot.copy_(value.reshape(()), non_blocking=True)
        if self._landed is not None:
            self._landed.record(self._stream)
        self.pending = True

    def read(self) -> list[float]:
        """The last started copy's values (waiting for that copy alone)."""
        if self._landed is not None:
            self._landed.synchronize()
        self.pending = False
        return self._host.tolist()


def pixels_kept(masks: torch.Tensor | None, pixels: torch.Tensor, sub: int) -> torch.Tensor | None:
    """[p k] bool: whether each ray's pixel is one to train on, by the training masks [N, H, W]
    bool (None: all, returns None), for ``pixels`` [p, 3] int32 (image, px, py) of k = sub²
    rays each (a gather on the device: no sync)."""
    if masks is None:
        return None
    image, px, py = pixels.long().unbind(1)
    return masks[image, py, px].repeat_interleave(sub * sub)


def rays_kept(ray_mask: torch.Tensor | None, kept: torch.Tensor | None) -> torch.Tensor | None:
    """The rays a loss counts: both masks [N] bool where given (None: all)."""
    if ray_mask is None or kept is None:
        return kept if ray_mask is None else ray_mask
    return ray_mask & kept
