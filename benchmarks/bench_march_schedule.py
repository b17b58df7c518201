"""Threads per ray of the march on whole views: the same rays marched with several segment
schedules (:class:`ngp_warp.ops.march_schedule.MarchSchedule`), timed alone and inside a view's render.

    python benchmarks/bench_march_schedule.py RUN --device cuda [--views 20]
        [--schedules 32:128 32:128:4194304 64:128 1000000000:1 32:128:4194304/0]

A schedule is ``SEGMENT_STEPS:MAX_SEGMENTS[:MOST_THREADS][/MASK_WORDS]``
(:class:`ngp_warp.ops.march_schedule.MarchSchedule`; MASK_WORDS, the most 64-bit words of a segment's
step mask, 0 to fill by marching again, defaults to 1). For each, over the first ``--views``
test views of the run (all sub-pixel rays of a view in one launch, as the evaluation marches
them): the segments per ray and threads per launch, ms per march (its count and fill, the device
synchronised), ms per rendered view (:meth:`Trainer.render_image`, as the evaluation renders it),
and the rays of the first view whose samples differ from the first schedule's (a step whose
midpoint lies within float rounding of an occupied cell's face may fall either side). Prints one
table.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from ngp_warp.cli.common import positive
from ngp_warp.ops import march_schedule, raymarch
from ngp_warp.outputs.renderer import subpixel_rays
from ngp_warp.training.checkpoint import load_trainer


def schedule(text: str) -> march_schedule.MarchSchedule:
    """The schedule ``SEGMENT_STEPS:MAX_SEGMENTS[:MOST_THREADS][/MASK_WORDS]``."""
    steps, _, words = text.partition("/")
    try:
        parts = [int(v) for v in steps.split(":")]
        mask_words = int(words) if words else 1
    except ValueError:
        parts, mask_words = [], -1
    if len(parts) not in (2, 3) or min(parts) < 1 or mask_words < 0:
        raise argparse.ArgumentTypeError(f"expected SEGMENT_STEPS:MAX_SEGMENTS[:MOST_THREADS][/MASK_WORDS], got {text!r}")
    return march_schedule.MarchSchedule(*parts, mask_words=mask_words)


def views_rays(trainer, views: int) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Each of the first ``views`` test views' rays [R, 3] (origins, directions), every sub-pixel."""
    split = trainer.scene.test
    return [subpixel_rays(cam["c2w"], cam["intrinsics"], cam["distortion"], cam["width"], cam["height"],
                          trainer.device, cam["fisheye"], trainer.config.supersample)
            for cam in (split.camera(i) for i in range(min(views, len(split.names))))]


def rays_that_differ(a: tuple[torch.Tensor, ...], b: tuple[torch.Tensor, ...]) -> int:
    """Rays whose samples differ between two marches of the same rays, each given as (ray_offsets
    [R + 1], ray_indices [S], t_starts [S]): in count, or (rays of equal counts) in any t_start."""
    (offsets_a, rays_a, t_a), (offsets_b, _, t_b) = a, b
    differ = torch.diff(offsets_a) != torch.diff(offsets_b)
    rows_a = (~differ[rays_a]).nonzero().squeeze(1)  # the samples of a's rays of equal counts
    ray = rays_a[rows_a]
    rows_b = offsets_b[ray].long() + rows_a - offsets_a[ray].long()  # the same sample of the same ray in b
    differ[ray[t_a[rows_a] != t_b[rows_b]]] = True
    return int(differ.sum())


def march_views(model, rays) -> None:
    """March every view's rays, each view's samples freed before the next is marched."""
    for rays_o, rays_d in rays:
        raymarch.ray_marching(rays_o, rays_d, model.grid, model.march, validate=False)


def timed(sync, work) -> float:
    sync()
    start = time.perf_counter()
    work()
    sync()
    return time.perf_counter() - start


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--views", type=positive(int), default=20)
    ap.add_argument("--schedules", type=schedule, nargs="+",
                    default=[schedule(s) for s in ("32:128", "32:128:4194304", "64:128", "1000000000:1")])
    args = ap.parse_args()
    trainer, _ = load_trainer(args.run / "checkpoint.pt", device=args.device)
    kind = "cpu" if trainer.device.type == "cpu" else "cuda"
    sync = torch.cuda.synchronize if kind == "cuda" else (lambda: None)
    model, split = trainer.model, trainer.scene.test
    rays = views_rays(trainer, args.views)
    step, max_step, _ = raymarch._march_steps(model.march, model.grid)
    march = model.march
    first, rows = None, []  # first: the first schedule's samples of the first view, on the host
    for sched in args.schedules:
        march_schedule.SCHEDULES[kind] = sched
        n_seg, seg_steps = march_schedule.ray_segments(sched, model.grid, march.near, march.far, step, march.cone_angle,
                                              max_step, rays[0][0].shape[0])
        view = raymarch.ray_marching(*rays[0], model.grid, march, validate=False)  # and the warm-up
        view = (view.ray_offsets.cpu(), view.ray_indices.cpu(), view.t_starts.cpu())
        differ = 0 if first is None else rays_that_differ(first, view)
        first = view if first is None else first
        march_s = timed(sync, lambda: march_views(model, rays))
        if kind == "cuda":
            torch.cuda.empty_cache()  # the renders size their chunks to the free memory
        cameras = [split.camera(i) for i in range(len(rays))]
        trainer.render_image(**cameras[0], background=trainer.view_background)
        render_s = timed(sync, lambda: [trainer.render_image(**c, background=trainer.view_background) for c in cameras])
        rows.append((sched, n_seg, seg_steps, n_seg * rays[0][0].shape[0], 1e3 * march_s / len(rays),
                     1e3 * render_s / len(rays), differ))
    print(f"{len(rays)} test views of {args.run} at {split.width}×{split.height}, {trainer.config.supersample}² rays a "
          f"pixel ({rays[0][0].shape[0]} rays a view), device {trainer.device}")
    print("| schedule | segments per ray | steps per segment | threads per launch | ms per march | ms per view | "
          "rays of the first view whose samples differ |\n|---|---:|---:|---:|---:|---:|---:|")
    for sched, n_seg, seg_steps, threads, march_ms, render_ms, differ in rows:
        spec = (f"{sched.segment_steps}:{sched.max_segments}" + (f":{sched.most_threads}" if sched.most_threads else "")
                + f"/{sched.mask_words}")
        print(f"| {spec} | {n_seg} | {seg_steps} | {threads} | {march_ms:.2f} | {render_ms:.2f} | {differ} |")


if __name__ == "__main__":
    main()
