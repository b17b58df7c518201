"""How a 360° capture with content beyond its subject trains, chosen by training: ``contraction_fit="probe"``.

Such a capture is either an object before a backdrop at infinity (the backdrop is a sky or an
environment: nothing triangulates beyond the subject) or a scene with content all around its
cameras (ground, walls). The first trains best bounded in instant-ngp's box of 32 with its
cascades (lego over an environment at 60 s on an H100: 33.4 dB against 30.0 contracted with the
box holding the cameras) and a learned colour at infinity for its backdrop (the demo object over
the environment: 28.0 ± 0.2 against 26.6 ± 3.8 without it, three runs each), the second
contracted (the unbounded scene: 31.5 against 29.2), and no rule on the cameras and images alone
told the two apart (benchmarks/NOTES.md). Training
does: contracted with the box the median camera sees at the centre (``"seen"``,
:func:`~ngp_warp.training.scene_defaults.contraction_box`), an object keeps its density inside
that box (its backdrop is the field's learned environment), while a scene around its cameras
puts a share of it outside. The density's share alone overlaps between the two (34 probes on an
H100, 14 seeds each of the demo object over an environment and the unbounded scene, 6 of the
room: 0.61–0.94 against 0.63–0.86 at 800 steps); its sum with the share of occupied cells
inside the box does not: at least 1.28 for the object by 1600 steps against at most 1.20 for the
other two at any of 400–1600 steps (benchmarks/RESULTS.md). The objects' sums rise with training,
the others' stay.

So the probe trains with ``"seen"`` for up to :data:`PROBE_STEPS` steps (at most 15 % of the
budget), reading the sum at each of :data:`PROBE_READS` and at its end, and starts again: bounded
in the box of :data:`OBJECT_AABB_SCALE` (or the ``aabb_scale`` given) at the first reading that
reaches :data:`PROBE_SCORE` (with ``field.environment`` on unless set), else contracted with the
box holding the cameras (``"cameras"``).
The new model takes the whole of a step budget (the probe's steps are not counted, so a resumed
run's step count stays the model's own), while a time budget counts the probe's seconds too (the
schedule runs over the whole time). A budget whose 15 % is under :data:`PROBE_MIN_STEPS`
steps trains with ``"cameras"`` without a probe, or after one that ran out of seconds first; a
probe whose pace says it is far too slow ends early (on 2 CPU cores, at about 8 steps a second,
a run under about 330 s).
"""

from __future__ import annotations

import dataclasses
import gc
from collections.abc import Callable

import torch

from ngp_warp.data.loading import Scene
from ngp_warp.ops.occupancy import OccupancyGrid
from ngp_warp.training.config import TrainConfig
from ngp_warp.training.scene_defaults import AUTO_FIT, PROBE_FIT, choose_contraction
from ngp_warp.training.trainer import Trainer

PROBE_STEPS = 1600  # the longest probe; an object is told at the first of PROBE_READS where its score is reached
PROBE_READS = (800, 1200)
PROBE_MIN_STEPS = 400  # fewer cannot tell (at 200 steps the objects' shares were 0.50 and 0.80)
PROBE_BUDGET_SHARE = 0.15  # the probe takes at most this share of the run's steps or seconds (1600 steps
                           # take 6–7 s of a 60 s run on an H100)
PROBE_SCORE = 1.25  # density share + occupied-cell share inside the box: an object from this on (module docstring)
OBJECT_AABB_SCALE = 32  # an object before a distant backdrop trains bounded in this box (colmap2nerf's default)
PACE_FROM = 50  # the probe's pace is read from this step on (the first steps load kernels and capture graphs)


@dataclasses.dataclass
class ProbeResult:
    """What the probe saw after ``steps`` steps (``seconds`` of training): the shares of the
    occupancy grid's density (``share``) and of its occupied cells (``cells``) inside the
    ``"seen"`` box, and what it chose: ``"bounded"`` (an object before a distant backdrop) or
    ``"cameras"`` (contracted, the inner box holding the cameras). The shares are None where the
    budget is too short for :data:`PROBE_MIN_STEPS` steps: ``steps`` and ``seconds`` are then 0
    when that was clear from the start, else what the probe spent before its time or its pace
    said so."""

    share: float | None
    cells: float | None
    steps: int
    seconds: float
    fit: str


def inner_cells(grid: OccupancyGrid) -> torch.Tensor:
    """bool [R³] on the grid's device, in the order of ``occs``: the cells of a contracted grid
    whose centre lies in the inner box, [-1, 1]³ of the grid's [-2, 2]³. ValueError for a grid
    without contraction."""
    if grid.contraction is None or grid.levels != 1:
        raise ValueError("inner_cells needs a contracted grid (one cascade)")
    r = grid.resolution
    axis = (torch.arange(r, device=grid.occs.device, dtype=torch.float32) + 0.5) * (4.0 / r) - 2.0
    inside = axis.abs() <= 1.0
    return (inside[:, None, None] & inside[None, :, None] & inside[None, None, :]).reshape(-1)


def density_share_inside(grid: OccupancyGrid) -> float:
    """The share of a contracted grid's density estimate (``occs`` ≥ 0; -1 marks unseen cells)
    in its :func:`inner_cells`. One host synchronisation."""
    inside = inner_cells(grid)
    density = grid.occs.clamp_min(0)
    total = float(density.sum())
    return float((density * inside).sum()) / total if total > 0 else 0.0


def shares_inside(grid: OccupancyGrid) -> tuple[float, float]:
    """(share of the density, share of the occupied cells) of a contracted grid in its
    :func:`inner_cells`. Two host synchronisations."""
    occupied = grid.occupied().reshape(-1)
    cells = float((occupied & inner_cells(grid)).sum()) / max(int(occupied.sum()), 1)
    return density_share_inside(grid), cells


def _tells_object(grid: OccupancyGrid) -> bool:
    """Whether the shares inside the inner box reach :data:`PROBE_SCORE` together (a NaN does not)."""
    share, cells = shares_inside(grid)
    return share + cells >= PROBE_SCORE


def _probe_length(config: TrainConfig) -> tuple[int, float | None]:
    """(steps, seconds or None) the probe may take of ``config``'s budget."""
    steps, seconds = config.budget()
    n = PROBE_STEPS if steps is None else min(PROBE_STEPS, int(steps * PROBE_BUDGET_SHARE))
    return n, None if seconds is None else seconds * PROBE_BUDGET_SHARE


def _spend(trainer: Trainer, seconds: float) -> None:
    """Count ``seconds`` of training as spent by ``trainer``, in its clock and its time budget."""
    trainer.train_seconds = seconds
    if trainer.config.seconds is not None:
        trainer.config.seconds = max(trainer.config.seconds - seconds, 1e-9)


def _probe_over(trainer: Trainer, seconds: float | None) -> Callable[[], bool]:
    """For :meth:`Trainer.train`'s ``until`` (checked at its readouts, step 1 among them): True

    * at a step of :data:`PROBE_READS` whose shares tell an object;
    * once the probe has spent ``seconds`` after its first step, which loads and compiles the
      kernels (with a cold kernel cache it took 6.4 s on an H100, more than a 60 s run's probe);
    * once it has spent ``seconds`` at the pace of its steps from :data:`PACE_FROM` on (read
      over as many again), its first steps counted at that pace: they capture graphs too;
    * once that pace says that :data:`PROBE_MIN_STEPS` steps would take more than ``seconds``,
      so a probe that cannot tell ends early.

    Without a time limit (``seconds`` None: a step budget) only a reading ends it."""
    first: float | None = None  # training seconds after the first step
    start: tuple[int, float] | None = None  # (step, training seconds) where the pace is read from

    def over() -> bool:
        nonlocal first, start
        steps, clock = trainer.step_count, trainer.train_seconds
        if steps in PROBE_READS and steps >= PROBE_MIN_STEPS and _tells_object(trainer.grid):
            return True
        if seconds is None:
            return False
        first = clock if first is None else first
        if clock - first >= seconds:
            return True
        if steps < PACE_FROM:
            return False
        start = (steps, clock) if start is None else start
        if steps < 2 * start[0]:
            return False
        pace = (clock - start[1]) / (steps - start[0])
        return pace * max(steps, PROBE_MIN_STEPS) >= seconds

    return over


def _probes(config: TrainConfig, scene: Scene) -> bool:
    """Whether ``config`` has ``scene`` probed: ``contraction_fit`` "probe" or "auto" where the
    scene's own rule contracts it (``contraction`` "auto", no contraction in its files)."""
    own_rule = config.contraction == "auto" and scene.contraction is None
    if not own_rule or choose_contraction(config.contraction, scene) is None:
        return False
    return config.contraction_fit in (PROBE_FIT, AUTO_FIT)


def probed_trainer(scene: Scene, config: TrainConfig | None, device: str | None = None,
                   make_trainer: Callable[[Scene, TrainConfig, str | None], Trainer] = Trainer,
                   show_progress: bool = False) -> tuple[Trainer, ProbeResult | None]:
    """A trainer for ``scene`` whose config's ``contraction_fit`` "probe" or "auto" has been
    decided (see the module docstring: bounded, or contracted with the box holding the cameras),
    ready for :meth:`Trainer.train` on the rest of the budget; other settings as
    ``make_trainer(scene, config, device)``; the probe's training with a progress bar ("probe")
    when ``show_progress``. Returns the trainer and what the probe saw: None where
    nothing is probed (:func:`_probes`); a share of None where the budget is too short for a
    probe."""
    config = config or TrainConfig()
    cameras = dataclasses.replace(config, contraction_fit="cameras")
    if not _probes(config, scene):
        return make_trainer(scene, cameras if config.contraction_fit == PROBE_FIT else config, device), None
    steps, seconds = _probe_length(config)
    if steps < PROBE_MIN_STEPS:  # too short a run to tell: the box holding the cameras
        return make_trainer(scene, cameras, device), ProbeResult(None, None, 0, 0.0, "cameras")
    # PROBE_SCORE was set on grids that count every point's density: grid_seen_only, which drops
    # the unseen parts of cells outside the box, would read a scene around its cameras as an object;
    # and on grids that cull: an open grid's occupied share says nothing
    probe = dataclasses.replace(config, contraction_fit="seen", grid_seen_only=False, occupancy_open_steps=0)
    trainer = make_trainer(scene, probe, device)
    trainer.train(show_progress=show_progress, stop=(steps, None), until=_probe_over(trainer, seconds), desc="probe")
    spent_steps, spent_seconds = trainer.step_count, trainer.train_seconds
    share, cells = shares_inside(trainer.grid) if spent_steps >= PROBE_MIN_STEPS else (None, None)
    bounded = share is not None and share + cells >= PROBE_SCORE  # a NaN trains contracted
    del trainer
    gc.collect()  # a trainer refers to itself (its step phases): free its device memory first
    if torch.cuda.is_available():
        torch.cuda.empty_cache()
    chosen = _bounded(config) if bounded else cameras
    trainer = make_trainer(scene, chosen, device)
    _spend(trainer, spent_seconds)  # the probe's seconds count in a time budget
    return trainer, ProbeResult(share, cells, spent_steps, spent_seconds, "bounded" if bounded else "cameras")


def _bounded(config: TrainConfig) -> TrainConfig:
    """``config`` for an object before a distant backdrop: no contraction, the box of
    :data:`OBJECT_AABB_SCALE` unless ``config`` gives an ``aabb_scale``, and a learned colour at
    infinity (the backdrop) unless ``config`` sets ``field.environment``."""
    box = OBJECT_AABB_SCALE if config.aabb_scale == "auto" else config.aabb_scale
    field = config.field
    if field.environment is None:
        field = dataclasses.replace(field, environment=True)
    return dataclasses.replace(config, contraction=None, aabb_scale=box, contraction_fit="cameras", field=field)
