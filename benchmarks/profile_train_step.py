"""Where a training step's time goes: warm step time, then torch.profiler over a few steps.

    python benchmarks/profile_train_step.py ../shared/data/lego_half [--device cuda]

Prints the warm per-step wall-clock, the top operators by device time, the device-busy time
per step and the kernel count per step (CUDA), so host-bound gaps show as wall − busy.
"""

from __future__ import annotations

import argparse
import time

import torch
from torch.autograd import DeviceType
from torch.profiler import ProfilerActivity, profile

from ngp_warp.data import load_scene
from ngp_warp.trainer import TrainConfig, Trainer


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--warmup", type=int, default=400)
    ap.add_argument("--timed", type=int, default=200)
    ap.add_argument("--profiled", type=int, default=20)
    args = ap.parse_args()

    trainer = Trainer(load_scene(args.scene), TrainConfig(steps=10**9), device=args.device)
    sync = torch.cuda.synchronize if trainer.device.type == "cuda" else (lambda: None)
    for _ in range(args.warmup):
        trainer.step()
    sync()
    start = time.perf_counter()
    for _ in range(args.timed):
        trainer.step()
    sync()
    print(f"warm step: {(time.perf_counter() - start) / args.timed * 1e3:.2f} ms, rays {trainer.n_rays}")

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if trainer.device.type == "cuda" else [])
    with profile(activities=activities) as prof:
        for _ in range(args.profiled):
            trainer.step()
        sync()
    events = prof.key_averages()
    sort = "cuda_time_total" if trainer.device.type == "cuda" else "cpu_time_total"
    print(events.table(sort_by=sort, row_limit=22, max_name_column_width=60))
    kernels = [e for e in events if e.device_type == DeviceType.CUDA]
    if kernels:
        busy = sum(e.self_device_time_total for e in kernels) / args.profiled
        count = sum(e.count for e in kernels) / args.profiled
        print(f"device busy per step: {busy / 1e3:.2f} ms; kernels per step: {count:.0f}")


if __name__ == "__main__":
    main()
