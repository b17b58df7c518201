"""Training speed and quality: test PSNR versus training wall-clock on one scene.

    python benchmarks/bench_train.py ../shared/data/lego_half [--device cuda] [--out bench_train]

Reports test PSNR (all test views, white background) at 5, 15, 30, 60, 120 and 300 s of
training wall-clock. Evaluation time is excluded: the clock stops while we evaluate. Kernel
compilation (a first run's cost; Warp caches kernels on disk) happens before the clock starts.
Also ms per step, rays and samples per step, peak GPU memory. Writes a JSON and a PNG plot.
Scenes with appearance codes are scored with the mean code on whole images (``psnr``) and, as
``ngp-warp eval`` scores them, with a code fitted on each view's left half, on its right half
(``psnr_fitted_right_half``).

By default one run is evaluated at every checkpoint, its learning-rate schedule spread over
the last one; ``--schedule-per-checkpoint`` trains a fresh run per checkpoint instead, each
with its schedule over its own budget (what ``ngp-warp train --seconds S`` gives).
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from ngp_warp.training.appearance_fit import right_half
from ngp_warp.training.config import TrainConfig, apply_overrides
from ngp_warp.data.loading import DataError, load_scene
from ngp_warp.outputs.evaluate import iter_test_renders
from ngp_warp.outputs.metrics import psnr
from ngp_warp.training.trainer import Trainer

sys.path.insert(0, str(Path(__file__).parent))
from grid_stats import format_stats, sample_stats  # noqa: E402


def _commit() -> str:
    """``NGP_WARP_COMMIT`` when set (trees copied without .git), else git's short HEAD."""
    if os.environ.get("NGP_WARP_COMMIT"):
        return os.environ["NGP_WARP_COMMIT"]
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=Path(__file__).parent).stdout.strip() or "unknown"
    except OSError:
        return "unknown"


def _plot(rows: list[dict], path: Path, title: str) -> bool:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot([r["seconds"] for r in rows], [r["psnr"] for r in rows], "o-")
    ax.set_xscale("log")
    ax.set_xlabel("training wall-clock (s, evaluation excluded)")
    ax.set_ylabel("test PSNR (dB)")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    return True


def scene_or_usage_error(ap: argparse.ArgumentParser, path: str, downscale: int = 1):
    """The scene at ``path``, or argparse's usage error with the loader's one-line reason."""
    try:
        return load_scene(path, downscale=downscale)
    except DataError as e:
        ap.error(str(e))


def warm_up(scene, cfg: TrainConfig, device: str) -> None:
    """Compile and load every kernel a run uses (a few steps and a render of a throwaway
    trainer), so that the clock measures training, not the first run's kernel compilation."""
    trainer = Trainer(scene, cfg, device=device)
    for _ in range(3):
        trainer.step()
    split = scene.test
    trainer.render_image(split.c2w[0], split.intrinsics[0], 8, 8)
    if trainer.device.type == "cuda":
        torch.cuda.synchronize(trainer.device)
    del trainer
    gc.collect()  # the captured graph holds a reference cycle: free its memory now


def view_scores(trainer: Trainer, test_every: int, fit_appearance: bool = False, spp: int = 1) -> dict[str, float]:
    """{test view name: PSNR}: the whole view, or with ``fit_appearance`` its right half with a
    code fitted on its left half (as ``ngp-warp eval`` scores a scene with codes)."""
    scores = {}
    for name, out, gt in iter_test_renders(trainer, every=test_every, fit_appearance=fit_appearance, spp=spp):
        rgb, gt = (right_half(out["rgb"]), right_half(gt)) if fit_appearance else (out["rgb"], gt)
        scores[name] = psnr(rgb, gt)
    return scores


def _worst(scores: dict[str, float]) -> str:
    name = min(scores, key=scores.get)
    return f"{Path(name).name} {scores[name]:.2f}"


def train_and_evaluate(trainer: Trainer, marks: list[float], test_every: int, spp: int = 1,
                       grid_stats: bool = False) -> list[dict]:
    """Train to each mark (seconds of training wall-clock), stopping the clock to evaluate; the
    learning-rate schedule runs over ``trainer.config.seconds``. ``spp`` > 1 also scores renders
    averaged over that many points per pixel (``psnr_spp``); ``grid_stats`` adds samples per ray
    and the grid's occupancy (:func:`grid_stats.sample_stats`) as ``grid``. Each row holds every
    view's score (``per_view``, and ``per_view_fitted_right_half`` with codes), and the printed
    line names the worst view: a view that collapses shows when it does."""
    schedule_seconds = trainer.config.seconds
    dev = trainer.device
    rows = []
    rays, samples, marched = [], [], []
    for mark in marks:
        steps0, t0 = trainer.step_count, trainer.train_seconds
        while trainer.train_seconds < mark:
            stats = trainer.step(progress=trainer.train_seconds / schedule_seconds)
            rays.append(stats["rays"])
            samples.append(stats["samples"])
            marched.append(stats["marched"])
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
        ms = 1000 * (trainer.train_seconds - t0) / max(trainer.step_count - steps0, 1)
        start = time.perf_counter()
        scores = view_scores(trainer, test_every)
        row = {
            "seconds": mark, "train_seconds": trainer.train_seconds, "steps": trainer.step_count,
            "psnr": float(np.mean(list(scores.values()))), "n_test": len(scores), "ms_per_step": ms,
            "rays_per_step": float(np.mean(rays[-50:])), "samples_per_step": float(np.mean(samples[-50:])),
            "marched_per_step": float(np.mean(marched[-50:])),
        }
        row["per_view"] = scores
        if spp > 1:
            row["psnr_spp"] = float(np.mean(list(view_scores(trainer, test_every, spp=spp).values())))
        if trainer.field.appearance is not None:  # what evaluate() reports: fitted code, right half
            row["per_view_fitted_right_half"] = fitted = view_scores(trainer, test_every, fit_appearance=True)
            row["psnr_fitted_right_half"] = float(np.mean(list(fitted.values())))
        if grid_stats:
            row["grid"] = sample_stats(trainer)
        row["eval_seconds"] = time.perf_counter() - start
        rows.append(row)
        print(f"{mark:6.0f} s  step {row['steps']:6d}  PSNR {row['psnr']:6.2f} dB  {ms:6.2f} ms/step  "
              f"rays {row['rays_per_step']:8.0f}  samples {row['samples_per_step']:9.0f}"
              f"  marched {row['marched_per_step']:9.0f}"
              + (f"  PSNR at {spp} spp {row['psnr_spp']:6.2f} dB" if spp > 1 else "")
              + (f"  right half, fitted code {row['psnr_fitted_right_half']:6.2f} dB"
                 if "psnr_fitted_right_half" in row else "")
              + f"  worst view {_worst(row.get('per_view_fitted_right_half', scores))}", flush=True)
        if grid_stats:
            print(f"        {format_stats(row['grid'])}", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--checkpoints", default="5,15,30,60,120,300", help="seconds at which to evaluate")
    ap.add_argument("--test-every", type=int, default=1, help="evaluate every k-th test view (1 = all)")
    ap.add_argument("--downscale", type=int, default=1)
    ap.add_argument("--target-samples", type=int)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a TrainConfig setting (field.KEY for the field), e.g. loss=huber; "
                         "seconds=S spreads the learning-rate schedule over S seconds (default: the last checkpoint)")
    ap.add_argument("--schedule-per-checkpoint", action="store_true",
                    help="train a fresh run per checkpoint, each with its schedule over that many seconds "
                         "(what a user who trains for that long gets), instead of one run evaluated along the way")
    ap.add_argument("--grid-stats", action="store_true",
                    help="also report samples per ray (median, mean) and the grid's occupancy per cascade")
    ap.add_argument("--out", default="bench_train")
    args = ap.parse_args()

    marks = [float(s) for s in args.checkpoints.split(",")]
    scene = scene_or_usage_error(ap, args.scene, args.downscale)
    try:
        cfg = apply_overrides(TrainConfig(seconds=marks[-1], target_samples=args.target_samples), args.set)
    except ValueError as e:
        ap.error(str(e))
    warm_up(scene, cfg, args.device)
    # One run evaluated at every mark, or a fresh run per mark with its schedule over that mark.
    runs = ([([mark], dataclasses.replace(cfg, seconds=mark)) for mark in marks] if args.schedule_per_checkpoint
            else [(marks, cfg)])
    rows = []
    for run_marks, run_cfg in runs:
        trainer = None
        gc.collect()  # drop the last run's graphs and memory first
        trainer = Trainer(scene, run_cfg, device=args.device)
        dev = trainer.device
        if not rows and dev.type == "cuda":
            torch.cuda.reset_peak_memory_stats(dev)
        rows += train_and_evaluate(trainer, run_marks, args.test_every, grid_stats=args.grid_stats)
    peak = torch.cuda.max_memory_allocated(dev) / 2**30 if dev.type == "cuda" else None
    name = torch.cuda.get_device_name(dev) if dev.type == "cuda" else "CPU"
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result = {"scene": str(args.scene), "device": name, "commit": _commit(), "date": time.strftime("%Y-%m-%d"),
              "command": " ".join(sys.argv), "config": dataclasses.asdict(trainer.config), "peak_gpu_memory_gib": peak, "rows": rows}
    (out / "bench_train.json").write_text(json.dumps(result, indent=2))
    plotted = _plot(rows, out / "psnr_vs_time.png", f"{Path(args.scene).name} on {name}")
    print()
    schedule = "one run per checkpoint" if args.schedule_per_checkpoint else f"one run, schedule over {marks[-1]:g} s"
    print(f"| train s | steps | test PSNR (dB) | ms/step | rays/step | samples/step trained | marched |   "
          f"({name}, commit {result['commit']}, {schedule})")
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        print(f"| {r['seconds']:.0f} | {r['steps']} | {r['psnr']:.2f} | {r['ms_per_step']:.2f} | "
              f"{r['rays_per_step']:.0f} | {r['samples_per_step']:.0f} | {r['marched_per_step']:.0f} |")
    if peak is not None:
        print(f"peak GPU memory {peak:.2f} GiB")
    print(f"wrote {out / 'bench_train.json'}" + (f" and {out / 'psnr_vs_time.png'}" if plotted else " (no matplotlib: no plot)"))


if __name__ == "__main__":
    main()
