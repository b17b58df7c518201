"""Where a data-parallel step's time goes: the warm step with and without each gradient reduction.

    torchrun --nproc-per-node 2 benchmarks/profile_data_parallel.py ../shared/data/lego_half [--set KEY=VALUE]

Every rank trains the same scene (``make_data_parallel``, as ``ngp-warp train --gpus N``). After
``--warmup`` steps, rank 0 prints one table row per variant of the reduction, timed in blocks of
``--block`` steps taken in turn, ``--rounds`` times, in the same continuing run (so a trend in
the sample count falls on every variant alike). Under ``--nproc-per-node 1``, ``none`` is one
GPU's step:

- ``reduced``: what training does (every gradient in one flat buffer, one all-reduce);
- ``none``: no reduction (each rank trains alone, the ranks still share the machine; the
  models drift apart: timing only).

Then the all-reduce of the flat buffer alone, in float32 and in bfloat16 (what half the bytes
on the wire would save), and a torch.profiler table of ``--profiled`` steps of ``both buckets`` on rank 0 (NCCL's kernels
included), so the reduction's device time and its overlap with the step can be read off.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
import torch.distributed as dist
from torch.autograd import DeviceType
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).parent))
from bench_train import scene_or_usage_error  # noqa: E402
from ngp_warp.training.config import TrainConfig, apply_overrides  # noqa: E402
from ngp_warp.training.distributed import join, leave, make_data_parallel  # noqa: E402
from ngp_warp.training.trainer import Trainer  # noqa: E402


def timed_steps(trainer: Trainer, steps: int) -> float:
    """Mean wall ms per step over ``steps`` steps, every rank synchronised before and after."""
    torch.cuda.synchronize()
    dist.barrier()
    start = time.perf_counter()
    for _ in range(steps):
        trainer.step(0.2)
    trainer.flush()
    torch.cuda.synchronize()
    dist.barrier()
    return (time.perf_counter() - start) / steps * 1e3


def all_reduce_ms(numel: int, dtype: torch.dtype, device: str, repeats: int = 50) -> float:
    """Mean ms of one all-reduce of ``numel`` elements of ``dtype`` (random values)."""
    t = torch.rand(numel, device=device).to(dtype)
    for _ in range(5):
        dist.all_reduce(t)
    torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(repeats):
        dist.all_reduce(t)
    torch.cuda.synchronize()
    return (time.perf_counter() - start) / repeats * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--warmup", type=int, default=1500)
    ap.add_argument("--block", type=int, default=50)
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--profiled", type=int, default=20)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args()
    device = join("cuda")
    rank, world = dist.get_rank(), dist.get_world_size()
    cfg = apply_overrides(TrainConfig(steps=10**9), args.set)
    trainer = Trainer(scene_or_usage_error(ap, args.scene), cfg, device=device)
    reducer = make_data_parallel(trainer)
    for _ in range(args.warmup):
        trainer.step(0.1)
    variants = (("reduced", reducer.finish), ("none", lambda: None))
    spent = dict.fromkeys((name for name, _ in variants), 0.0)
    for _ in range(args.rounds):
        for name, reduction in variants:
            trainer.gradient_reduction = reduction
            spent[name] += timed_steps(trainer, args.block) / args.rounds
    trainer.gradient_reduction = reducer.finish
    size = sum(p.numel() for p in reducer.params)
    fp32, bf16 = (all_reduce_ms(size, d, device) for d in (torch.float32, torch.bfloat16))
    if rank == 0:
        print(f"{world} ranks, {torch.cuda.get_device_name()}; gradients {size} floats ({size * 4 / 2**20:.0f} MiB)")
        print("| reduction | ms per step |\n| --- | ---: |")
        for name, ms in spent.items():
            print(f"| {name} | {ms:.3f} |")
        print(f"all-reduce of the gradients alone: float32 {fp32:.3f} ms, bfloat16 {bf16:.3f} ms")
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        for _ in range(args.profiled):
            trainer.step(0.2)
        torch.cuda.synchronize()
    if rank == 0:
        events = prof.key_averages()
        print(events.table(sort_by="cuda_time_total", row_limit=15, max_name_column_width=60))
        busy = sum(e.self_device_time_total for e in events if e.device_type == DeviceType.CUDA)
        print(f"device busy per step (NCCL's kernels included): {busy / args.profiled / 1e3:.2f} ms")
    leave()


if __name__ == "__main__":
    main()
