"""How :func:`ngp_warp.ops.raymarch.ray_marching` spreads a launch over threads: the segments
of steps each thread marches (:class:`MarchSchedule`, one per device kind in :data:`SCHEDULES`),
the count's step masks the fill writes from, and when positions and directions take a pass of
their own. None of it changes the samples."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ngp_warp.ops.occupancy import OccupancyGrid

NO_CAP = 2**31 - 1  # no bound: samples per ray, steps per segment, samples per launch


@dataclass(frozen=True)
class MarchSchedule:
    """Threads per ray for fixed steps: a ray's steps are split into segments of at least
    ``segment_steps`` steps, at most ``max_segments`` of them per ray, and with ``most_threads``
    (None: no such bound) no more segments than keep the threads of one launch within it (at
    least one segment per ray). A segment of at most ``mask_words`` × 64 steps keeps its kept
    steps as a bit mask (a word per 64 steps), from which the fill writes the samples instead of
    marching again. From ``points_apart_from`` samples on (None: never) the fill writes only
    the samples' rays and intervals, and a second pass, one thread per sample, their positions
    and directions."""

    segment_steps: int
    max_segments: int
    most_threads: int | None = None
    mask_words: int = 1
    points_apart_from: int | None = None


# The GPU needs many short segments to fill its threads when a launch marches few rays (a
# training step's); a view's hundreds of thousands of rays fill it with a few segments each, and
# every segment costs a ray setup. On the CPU the rays alone already keep every core busy. The
# CPU's fill is bound by its march, so its segments (up to 1024 steps) keep masks; the GPU's
# fill of a view's longer segments is bound by its writes, and a mask of several words there
# gains nothing (benchmarks/RESULTS.md, "A view's march: where the fill's time goes"). There a
# thread's writes, one sample after another, scatter over memory: a view's positions and
# directions (not a training step's, whose launches are small) take a pass of their own.
SCHEDULES = {"cpu": MarchSchedule(512, 8, mask_words=16),
             "cuda": MarchSchedule(32, 128, 1 << 22, points_apart_from=1 << 20)}


def steps_over(t_a: float, t_b: float, step: float, cone_angle: float, max_step: float) -> float:
    """The steps from t_a to t_b ≥ t_a (not rounded) of t_{k+1} = t_k + clip(t_k·cone_angle,
    step, max_step): fixed steps up to step/cone_angle, steps growing by 1 + cone_angle up to
    max_step/cone_angle, then steps of max_step."""
    if cone_angle == 0:
        return (t_b - t_a) / step
    fixed_end, growing_end = step / cone_angle, max_step / cone_angle
    n = max(min(t_b, fixed_end) - t_a, 0.0) / step
    lo, hi = max(t_a, fixed_end), min(t_b, growing_end)
    if hi > lo:
        n += math.log(hi / lo) / math.log1p(cone_angle)
    return n + max(t_b - max(t_a, growing_end), 0.0) / max_step


def ray_segments(schedule: MarchSchedule, grid: OccupancyGrid, near: float, far: float, step: float,
                 cone_angle: float, max_step: float, n_rays: int) -> tuple[int, int]:
    """(segments per ray, steps per segment) for a launch of ``n_rays`` rays. A ray inside the
    coarsest cascade box spans at most min(far − near, box diagonal) when |d| = 1, and takes the
    most steps when that span starts at near (steps only grow with t): :func:`steps_over` + 1
    (the last segment takes any remainder). Contracted grids are marched by one thread per ray
    (one segment without a step bound: NO_CAP)."""
    if grid.contraction is not None:
        return 1, NO_CAP
    lo, hi = grid.aabb_host[:3], grid.aabb_host[3:]
    diagonal = math.dist(lo, hi) * 2 ** (grid.levels - 1)
    steps = steps_over(near, near + min(far - near, diagonal), step, cone_angle, max_step) + 1
    n_seg = int(min(max(steps / schedule.segment_steps, 1), schedule.max_segments))
    if schedule.most_threads is not None:
        n_seg = max(1, min(n_seg, schedule.most_threads // max(n_rays, 1)))
    return n_seg, math.ceil(steps / n_seg)
