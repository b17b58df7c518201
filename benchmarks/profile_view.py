"""Where one inference view's time goes: wall-clock against device time per kernel.

    python benchmarks/profile_view.py RUN [--size 800x800] [--repeats 5] [--top 12]

Renders the first test camera of the trained run ``RUN`` (as ``bench_view.py`` does, one ray
per pixel) once to
warm up, then ``--repeats`` times under torch.profiler (CUDA activity, Warp's kernels included).
Prints the wall-clock per view, the device time per view summed over all kernels, and the
kernels that take the most of it (name, ms per view, launches per view). Wall minus device is
time the GPU waits for the host or a sync.
"""

from __future__ import annotations

import argparse
import collections
import time
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

from ngp_warp.training.checkpoint import load_trainer
from ngp_warp.cli import CHECKPOINT


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", help="a trained output folder")
    ap.add_argument("--size", default="800x800", help="WxH")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--top", type=int, default=12)
    ap.add_argument("--first-round", default="auto", help="render_view's first_round: auto, a count, or 0 (None)")
    args = ap.parse_args()
    width, height = (int(v) for v in args.size.lower().split("x"))
    first_round = args.first_round if args.first_round == "auto" else int(args.first_round) or None
    trainer = load_trainer(Path(args.run) / CHECKPOINT, device="cuda")[0]
    split = trainer.scene.test
    intrinsics = split.intrinsics[0] * torch.tensor([width / split.width, height / split.height] * 2)
    distortion = split.distortion[0] if split.has_distortion else None

    def render() -> dict:
        return trainer.render_image(split.c2w[0], intrinsics, width, height, distortion=distortion,
                                    fisheye=split.fisheye, supersample=1, first_round=first_round)

    render()  # warm-up, and the model's last view for first_round="auto"
    torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(args.repeats):
        out = render()
    torch.cuda.synchronize()
    wall = (time.perf_counter() - t0) / args.repeats
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(args.repeats):
            render()
        torch.cuda.synchronize()
    per_kernel: collections.Counter = collections.Counter()
    launches: collections.Counter = collections.Counter()
    for event in prof.events():
        if event.device_type == torch.autograd.DeviceType.CUDA:
            per_kernel[event.name[:60]] += event.device_time * 1e-3 / args.repeats
            launches[event.name[:60]] += 1 / args.repeats
    rays = width * height
    print(f"{args.run} {width}x{height}: wall {wall * 1e3:.2f} ms/view, device {sum(per_kernel.values()):.2f} ms/view, "
          f"first round {args.first_round or '-'}, marched/ray {out['n_marched'] / rays:.1f}, "
          f"encoded/ray {out['n_encoded'] / rays:.1f}, shaded/ray {out['n_shaded'] / rays:.1f}")
    print(f"{'kernel':<60} {'ms/view':>8} {'launches':>8}")
    for name, ms in per_kernel.most_common(args.top):
        print(f"{name:<60} {ms:>8.3f} {launches[name]:>8.1f}")


if __name__ == "__main__":
    main()
