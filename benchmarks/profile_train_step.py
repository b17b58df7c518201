"""Where a training step's time goes: warm step time, then torch.profiler over a few steps.

    python benchmarks/profile_train_step.py ../shared/data/lego_half [--device cuda]

Prints the warm per-step wall-clock, the host time of each phase of a step (nothing syncs
inside a phase except the march, which waits for the device), the top operators by device
time, the device-busy time per step and the kernel count per step (CUDA), so host-bound gaps
show as wall − busy, and on CUDA the top operators by host time. ``--set KEY=VALUE`` as in
``bench_train.py``.
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict

import torch
from torch.autograd import DeviceType
from torch.profiler import ProfilerActivity, profile

import ngp_warp.ops.render
from bench_train import scene_or_usage_error
from ngp_warp.training.config import TrainConfig, apply_overrides
from ngp_warp.training.trainer import Trainer

# Trainer phases (ngp_warp.training.train_step.StepPhases) → table rows; indented rows run inside the
# unindented one above them (not added to the step's total).
PHASE_ROWS = {
    "grid_update": "occupancy grid update",
    "sample_batch": "sample batch",
    "render": "render (all of it)",
    "optimizer_update": "    optimizer and MLP average (the last step's, queued in the march or a grid refresh)",
    "density": "  density passes (no grad; the grid refresh's included)",
    "field": "  field forward",
    "loss": "loss forward",
    "distortion": "distortion forward",
    "backward": "backward (autograd engine)",
}


def time_phases(trainer: Trainer) -> dict[str, float]:
    """Time the step's phases (through :meth:`Trainer.instrument`, and the march and prune
    inside the render op) so that their host seconds add up in the returned dict."""
    spent: dict[str, float] = defaultdict(float)

    def timed(name, fn):
        def wrapper(*args, **kwargs):
            start = time.perf_counter()
            result = fn(*args, **kwargs)
            spent[name] += time.perf_counter() - start
            return result
        return wrapper

    trainer.instrument(lambda phase, fn: timed(PHASE_ROWS[phase], fn))
    # inside the render op: its module's own names for the march and the pruning
    ngp_warp.ops.render.ray_marching = timed("  march (+ its sync)", ngp_warp.ops.render.ray_marching)
    ngp_warp.ops.render.prune_samples = timed("  prune", ngp_warp.ops.render.prune_samples)
    return spent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--warmup", type=int, default=400)
    ap.add_argument("--timed", type=int, default=200)
    ap.add_argument("--profiled", type=int, default=20)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args()

    try:
        cfg = apply_overrides(TrainConfig(steps=10**9), args.set)
    except ValueError as e:
        ap.error(str(e))
    trainer = Trainer(scene_or_usage_error(ap, args.scene), cfg, device=args.device)
    spent = time_phases(trainer)
    sync = torch.cuda.synchronize if trainer.device.type == "cuda" else (lambda: None)
    for _ in range(args.warmup):
        trainer.step()
    sync()
    spent.clear()
    start = time.perf_counter()
    counts = [trainer.step() for _ in range(args.timed)]
    sync()
    step_ms = (time.perf_counter() - start) / args.timed * 1e3
    mean = {k: sum(c[k] for c in counts) / len(counts) for k in ("rays", "samples", "marched")}
    print(f"warm step: {step_ms:.2f} ms; per step: rays {mean['rays']:.0f}, samples marched "
          f"{mean['marched']:.0f}, trained on {mean['samples']:.0f}")
    print("| phase | host ms per step |\n| --- | ---: |")
    for name, seconds in spent.items():
        print(f"| {name} | {seconds / args.timed * 1e3:.3f} |")
    top = sum(seconds for name, seconds in spent.items() if not name.startswith(" ")) / args.timed * 1e3
    print(f"| rest of the step (wall − the phases above) | {step_ms - top:.3f} |")

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if trainer.device.type == "cuda" else [])
    with profile(activities=activities) as prof:
        for _ in range(args.profiled):
            trainer.step()
        sync()
    events = prof.key_averages()
    sort = "cuda_time_total" if trainer.device.type == "cuda" else "cpu_time_total"
    print(events.table(sort_by=sort, row_limit=40, max_name_column_width=60))
    if trainer.device.type == "cuda":  # where the host time goes (a host-bound step)
        print(events.table(sort_by="self_cpu_time_total", row_limit=30, max_name_column_width=60))
    kernels = [e for e in events if e.device_type == DeviceType.CUDA]
    if kernels:
        busy = sum(e.self_device_time_total for e in kernels) / args.profiled
        count = sum(e.count for e in kernels) / args.profiled
        print(f"device busy per step: {busy / 1e3:.2f} ms; kernels per step: {count:.0f}")


if __name__ == "__main__":
    main()
