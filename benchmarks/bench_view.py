"""Benchmark the inference renderer: one view of a trained run at several resolutions.

Each row renders the first test camera (its intrinsics scaled to the size) with
:meth:`Trainer.render_image` (weight average, ``--supersample``² rays per pixel, default one,
each ``--first-round`` given),
``--repeats`` times after one warm-up, the device synchronised; it reports the median time,
rays per second (pixels × sub-rays) and the samples per ray marched, encoded (hash grid and
density MLP) and shaded (colour MLP).

    python benchmarks/bench_view.py runs/lego --sizes 800x800 --device cuda
    python benchmarks/bench_view.py runs/fox --sizes 1920x1080 --device cuda
    python benchmarks/bench_view.py --sizes 100x100 200x200 --device cpu   # trains a demo run first

Without a run folder it trains the procedural demo scene (100×100 views) with the demo's
settings for ``--train-seconds`` in a temporary folder.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import torch

from ngp_warp.training.checkpoint import load_trainer
from ngp_warp.cli import CHECKPOINT
from ngp_warp.training.demo import demo_config
from ngp_warp.data.loading import load_scene
from ngp_warp.outputs.renderer import auto_first_round
from ngp_warp.data.scene import write_demo_scene
from ngp_warp.training.trainer import Trainer


def first_round(text: str) -> int | str:
    return text if text == "auto" else int(text)


def size(text: str) -> tuple[int, int]:
    width, height = (int(v) for v in text.lower().split("x"))
    return width, height


def demo_trainer(device: str, seconds: float, folder: Path) -> Trainer:
    scene = load_scene(write_demo_scene(folder / "scene"))
    trainer = Trainer(scene, demo_config(device, None, seconds, 0), device=device)
    trainer.train(show_progress=False)
    return trainer


def time_view(trainer: Trainer, width: int, height: int, repeats: int, supersample: int,
              first_round: int | str | None = "auto") -> dict:
    split = trainer.scene.test
    scale = torch.tensor([width / split.width, height / split.height] * 2)
    c2w, intrinsics = split.c2w[0], split.intrinsics[0] * scale
    distortion = split.distortion[0] if split.has_distortion else None

    def render() -> dict:
        out = trainer.render_image(c2w, intrinsics, width, height, distortion=distortion, fisheye=split.fisheye,
                                   supersample=supersample, first_round=first_round)
        if trainer.device.type == "cuda":
            torch.cuda.synchronize(trainer.device)
        return out

    render()  # warm-up: kernels compiled and loaded, memory pools filled, the model's last view set
    times = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = render()
        times.append(time.perf_counter() - t0)
    rays = width * height * supersample ** 2
    ms = statistics.median(times) * 1e3
    return {"size": f"{width}x{height}", "rays": rays, "ms": ms, "rays_per_s": rays / (ms / 1e3),
            "marched_per_ray": out["n_marched"] / rays, "encoded_per_ray": out["n_encoded"] / rays,
            "shaded_per_ray": out["n_shaded"] / rays}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", nargs="?", help="a trained output folder (default: train the demo scene)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--sizes", nargs="+", type=size, default=[(100, 100), (200, 200)], metavar="WxH")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--supersample", type=int, default=1, help="rays per pixel: this squared (default 1)")
    parser.add_argument("--first-round", type=first_round, nargs="+", default=["auto"], metavar="K",
                        help="render_view's first_round, one row each: auto (default), a count, or 0 (None: "
                             "every marched sample at once)")
    parser.add_argument("--train-seconds", type=float, default=150.0, help="demo training budget (no run given)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        if args.run:
            trainer = load_trainer(Path(args.run) / CHECKPOINT, device=args.device)[0]
            what = args.run
        else:
            trainer = demo_trainer(args.device, args.train_seconds, Path(tmp))
            what = f"demo scene, {trainer.step_count} steps in {trainer.train_seconds:.0f} s"
        rows = [{**time_view(trainer, w, h, args.repeats, args.supersample, k or None),
                 "first_round": k if k != "auto" else f"auto {auto_first_round(trainer.model.view_shaded_per_ray)}"}
                for w, h in args.sizes for k in args.first_round]
    name = torch.cuda.get_device_name(trainer.device) if trainer.device.type == "cuda" else f"{torch.get_num_threads()} CPU threads"
    print(f"{what}; {trainer.device} ({name}); {args.supersample}² rays per pixel; "
          f"median of {args.repeats}")
    head = (f"{'size':>10} {'1st round':>10} {'rays':>9} {'ms/view':>9} {'Mrays/s':>8} {'marched/ray':>12} "
            f"{'encoded/ray':>12} {'shaded/ray':>11}")
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r['size']:>10} {r['first_round'] or '-':>10} {r['rays']:>9} {r['ms']:>9.1f} {r['rays_per_s'] / 1e6:>8.3f} "
              f"{r['marched_per_ray']:>12.1f} {r['encoded_per_ray']:>12.1f} {r['shaded_per_ray']:>11.1f}")


if __name__ == "__main__":
    main()
