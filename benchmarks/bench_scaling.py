"""One GPU against several: data-parallel training and fit-many, through the commands a user runs.

    python benchmarks/bench_scaling.py --scene ../shared/data/lego_half --gpus 1,2 --seconds 8,15 \
        --target 35 [--variant split=target_samples=131072 ...] [--fit-many 8 --fit-many-steps 3000] \
        [--device cuda] [--out bench_scaling]

Prints two tables:

1. ``ngp-warp train SCENE --seconds S --gpus G --no-video`` for every G and S: PSNR, steps,
   ms per step, the wall clock by phase (metrics.json's ``wall_seconds``: start-up, training,
   checkpoint, evaluation), and per G the seconds of training to reach ``--target`` dB, read off
   the line through the two budgets that bracket it (or "not reached"). Each ``--variant
   LABEL=KEY=VALUE[,KEY=VALUE]`` adds rows of every G above 1 with those ``--set`` settings.
2. ``ngp-warp fit-many`` over ``--fit-many`` generated demo scenes of unequal size (12 to 48 views
   at 48 to 96 pixels) for every G: wall seconds, scenes per hour, each rank's idle seconds
   (summary.json), and scenes per hour against one rank.

With ``--device cpu`` the ranks are CPU processes joined by gloo (a smoke run of the same paths).
The all-reduce's share of a step: ``profile_data_parallel.py``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path


def run(command: list[str]) -> None:
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"failed ({done.returncode}): {' '.join(command)}\n{done.stderr[-2000:]}")


def train_row(scene: Path, out: Path, gpus: int, seconds: float, device: str, label: str = "",
              settings: tuple[str, ...] = ()) -> dict:
    sets = [arg for setting in settings for arg in ("--set", setting)]
    run(["ngp-warp", "train", str(scene), "--out", str(out), "--seconds", str(seconds), "--gpus", str(gpus),
         "--device", device, "--no-video", "--quiet", "--overwrite", *sets])
    metrics = json.loads((out / "metrics.json").read_text())
    row = {"gpus": gpus, "label": label, "seconds": seconds, "psnr": metrics["psnr"], "steps": metrics["steps"],
           "ms": 1000.0 * metrics["train_seconds"] / max(metrics["steps"], 1), "wall": metrics["wall_seconds"]}
    print(json.dumps(row), flush=True)  # kept if a later run fails
    return row


def time_to(rows: list[dict], target: float) -> str:
    """Seconds of training at which the PSNR line through two budgets crosses ``target``."""
    rows = sorted(rows, key=lambda r: r["seconds"])
    for a, b in zip(rows, rows[1:]):
        if a["psnr"] < target <= b["psnr"]:
            seconds = a["seconds"] + (target - a["psnr"]) * (b["seconds"] - a["seconds"]) / (b["psnr"] - a["psnr"])
            return f"reach {target:g} dB after {seconds:.1f} s of training"
    if rows and rows[0]["psnr"] >= target:
        return f"reach {target:g} dB within {rows[0]['seconds']:g} s of training"
    return f"do not reach {target:g} dB within {rows[-1]['seconds']:g} s" if rows else "no runs"


def training_table(rows: list[dict], target: float) -> str:
    lines = ["| GPUs | variant | seconds | PSNR | steps | ms/step | start-up | training | checkpoint | evaluation | wall |",
             "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        w = r["wall"]
        lines.append(f"| {r['gpus']} | {r['label']} | {r['seconds']:g} | {r['psnr']:.2f} | {r['steps']} | {r['ms']:.2f} "
                     f"| {w['start_up']:.1f} | {w['training']:.1f} | {w['checkpoint']:.1f} | {w['evaluation']:.1f} "
                     f"| {sum(w.values()):.1f} |")
    for gpus, label in sorted({(r["gpus"], r["label"]) for r in rows}):
        same = [r for r in rows if r["gpus"] == gpus and r["label"] == label]
        lines.append(f"\n{gpus} GPU(s) {label}: {time_to(same, target)}")
    return "\n".join(lines)


def write_scenes(folder: Path, count: int, device: str) -> Path:
    """``count`` demo scenes of unequal size under ``folder`` (generated once, rendered on
    ``device``); the glob of them."""
    from ngp_warp.data.scene import write_demo_scene

    for k in range(count):
        scene = folder / f"scene{k:02d}"
        if not scene.exists():
            write_demo_scene(scene, width=48 + 48 * (k % 2), height=48 + 48 * (k % 2), n_train=12 + 12 * (k % 4),
                             n_test=2, seed=k, supersample=1, device=device)
    return folder / "scene*"


def fit_many_table(pattern: Path, out: Path, gpus_list: list[int], steps: int, device: str) -> str:
    lines = ["| GPUs | wall s | scenes per hour | against 1 rank | idle s per rank |", "|---:|---:|---:|---:|---|"]
    base = None
    for gpus in gpus_list:
        run(["ngp-warp", "fit-many", str(pattern), "--out", str(out / f"gpus{gpus}"), "--steps", str(steps),
             "--gpus", str(gpus), "--device", device, "--no-video", "--quiet", "--overwrite"])
        summary = json.loads((out / f"gpus{gpus}" / "summary.json").read_text())
        rate = summary["scenes_per_hour"]
        base = rate if base is None else base
        idle = ", ".join(f"{r['idle_seconds']:.1f}" for r in summary["per_rank"])
        lines.append(f"| {gpus} | {summary['wall_seconds']:.1f} | {rate:.0f} | {rate / base:.2f}× | {idle} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", type=Path, required=True)
    parser.add_argument("--gpus", default="1,2", help="comma-separated rank counts")
    parser.add_argument("--seconds", default="8,15", help="comma-separated training budgets ('': fit-many only)")
    parser.add_argument("--target", type=float, default=35.0, help="the PSNR whose time is read off")
    parser.add_argument("--variant", action="append", default=[], metavar="LABEL=KEY=VALUE[,KEY=VALUE]",
                        help="rows of every rank count above 1 with these settings")
    parser.add_argument("--fit-many", type=int, default=0, help="generated scenes for fit-many (0: skip)")
    parser.add_argument("--fit-many-steps", type=int, default=3000)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--out", type=Path, default=Path("bench_scaling"))
    args = parser.parse_args()
    gpus_list = [int(g) for g in args.gpus.split(",")]
    variants = [("defaults", ())] + [(v.split("=", 1)[0], tuple(v.split("=", 1)[1].split(","))) for v in args.variant]
    rows = [train_row(args.scene, args.out / f"train-g{g}-{label}-s{s}", g, float(s), args.device, label, sets)
            for g in gpus_list for label, sets in (variants if g > 1 else variants[:1])
            for s in args.seconds.split(",") if s]
    if rows:
        print(training_table(rows, args.target))
    if args.fit_many:
        pattern = write_scenes(args.out / "scenes", args.fit_many, args.device)
        print("\n" + fit_many_table(pattern, args.out / "fit-many", gpus_list, args.fit_many_steps, args.device))
    (args.out / "scaling.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    sys.exit(main())
