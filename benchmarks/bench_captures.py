"""The capture benchmark: scenes as people bring them, with exact ground truth, trained through
the command a user runs (``ngp-warp train SCENE --seconds S``, defaults), one table.

    python benchmarks/bench_captures.py --lego ../shared/data/lego_half --fox ../shared/data/fox \
        --seconds 60 [--scenes demo-colmap,unbounded-colmap] [--runs 3] [--compare contraction=none] \
        [--downscale 4] [--device cpu] [--seed 0] [--gpus 2]

Scenes (every 8th frame held out, sorted by name; ``capture_scenes.py`` writes the forms):

* ``demo-colmap`` / ``demo-colmap-sky`` / ``demo-ngp``: the built-in demo scene (60 views at
  100×100) as a COLMAP model over white, the same over the unbounded scene's environment at
  infinity, and as an instant-ngp transforms.json over white;
* ``lego-colmap`` / ``lego-colmap-sky`` / ``lego-ngp``: lego_half's train and test views, every
  2nd (150 at 400×400), in the same three forms (``--lego``);
* ``demo-nerf-synthetic`` / ``lego-nerf-synthetic``: the same views as a NeRF-synthetic folder
  whose test split is the frames the captures hold out (the reference a capture form is held to);
* ``unbounded-colmap``: the built-in unbounded scene (60 train + 10 test views) as a COLMAP model;
* ``room-colmap``: the demo scene in its textured room (60 views at 100×100) as a COLMAP model;
* ``hall-colmap``: the same in a wider room (wall at 10 against 6, other noise and cameras);
* ``fox``: instant-ngp's fox as it ships (``--fox``).

Columns: whole-image PSNR (with the nearest training camera's appearance code where codes are on;
then with the mean code), the right-half
PSNR with a code fitted on the left half (codes on), SSIM (as metrics.json: right half where
codes are on), steps, ms per step, trained samples per ray, the contraction the run used.
``OUT/captures.png`` shows each row's first held-out view: ground truth, render, depth.
``--compare KEY=VALUE`` adds a row per scene trained with that setting, and a second table: its
whole-image PSNR minus the defaults' trained with the same seeds (mean ± sd over the pairs). A
third table gives each held-out view's PSNR (right half with codes on), the mean over the runs,
where a scene has at most 12 of them (fox's floaters show in one view). ``--gpus N`` trains N
runs at once, one per CUDA GPU (two processes on one host slow each other's host-bound steps by
about 5–10 %). Writes ``OUT/captures.json`` with every run.
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import os
import queue
import statistics
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))
from capture_scenes import write_capture  # noqa: E402

SCENES = ("demo-colmap", "demo-colmap-sky", "demo-ngp", "demo-nerf-synthetic", "lego-colmap", "lego-colmap-sky",
          "lego-ngp", "lego-nerf-synthetic", "unbounded-colmap", "room-colmap", "hall-colmap", "fox")


HALL_RADIUS = 10.0  # the hall's wall, against the room's 6 (cameras at 4 from the centre)


def write_room(folder: Path, radius: float | None = None, seed: int = 0) -> Path:
    """The demo scene in its textured room (wall ``radius``, the room's own if None; noise and
    cameras by ``seed``) as an opaque NeRF-synthetic folder (50 train, 10 test)."""
    from ngp_warp.data import scene as demo
    from ngp_warp.data.scene_folder import write_split

    def render(c2w: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
        return demo.render_room_views(c2w, intrinsics, 100, 100, seed=seed, radius=radius or demo.ROOM_RADIUS)

    folder.mkdir(parents=True)
    for split, c2w in zip(("train", "test"), demo.demo_cameras(50, 10, seed=seed)):
        write_split(folder, split, c2w, 100, 100, demo.CAMERA_ANGLE_X, render, {})
    return folder


def source(name: str, work: Path, args) -> Path:
    """The NeRF-synthetic folder a scene is written from (generated once into ``work``)."""
    base = name.split("-")[0]
    folder = work / f"src-{base}"
    if base == "lego":
        if args.lego is None:
            raise SystemExit(f"{name} needs --lego")
        return args.lego
    if not folder.exists():
        if base == "demo":
            from ngp_warp.data.scene import write_demo_scene

            write_demo_scene(folder, n_train=50, n_test=10)
        elif base == "unbounded":
            from ngp_warp.data.scene_unbounded import write_unbounded_scene

            write_unbounded_scene(folder, n_train=60, n_test=10)
        elif base == "hall":
            write_room(folder, radius=HALL_RADIUS, seed=1)
        else:
            write_room(folder)
    return folder


def scene_folder(name: str, work: Path, args) -> Path:
    """The capture folder of scene ``name``, written once into ``work``."""
    if name == "fox":
        if args.fox is None:
            raise SystemExit("fox needs --fox")
        return args.fox
    folder = work / name
    if not folder.exists():
        form = name.split("-", 1)[1]
        every = 2 if name.startswith("lego") else 1
        write_capture(source(name, work, args), folder, form, every)
    return folder


def train(scene: Path, out: Path, args, seed: int, settings: list[str], gpu: str | None = None) -> dict:
    """One ``ngp-warp train`` run (on the CUDA GPU of id ``gpu`` alone where given); its
    metrics.json with the run's contraction added."""
    command = ["ngp-warp", "train", str(scene), "--out", str(out), "--seconds", str(args.seconds), "--seed", str(seed),
               "--no-video", "--quiet", "--overwrite", "--device", args.device, "--downscale", str(args.downscale)]
    for setting in settings:
        command += ["--set", setting]
    env = None if gpu is None else {**os.environ, "CUDA_VISIBLE_DEVICES": str(gpu)}
    done = subprocess.run(command, capture_output=True, text=True, env=env)
    if done.returncode != 0:
        print(done.stdout + done.stderr, file=sys.stderr)
        return {"error": (done.stderr.strip().splitlines() or ["failed"])[-1]}
    metrics = json.loads((out / "metrics.json").read_text())
    config = torch.load(out / "checkpoint.pt", map_location="cpu", weights_only=False)["train_config"]
    metrics["contraction"] = config["contraction"] or "none"
    print(f"{out.name}: {whole_psnr(metrics):.2f} dB, {metrics['steps']} steps", file=sys.stderr, flush=True)
    return metrics


def train_all(jobs: list[tuple[Path, Path, int, list[str]]], args) -> list[dict]:
    """:func:`train` each (scene, out, seed, settings) of ``jobs``, ``args.gpus`` at a time, each
    on a GPU of its own (of ``args.gpu_ids``); the metrics in the order of ``jobs``."""
    if args.gpus <= 1:
        return [train(*job[:2], args, *job[2:]) for job in jobs]
    free = queue.SimpleQueue()
    for gpu in args.gpu_ids[:args.gpus]:
        free.put(gpu)

    def on_a_free_gpu(job):
        gpu = free.get()
        try:
            return train(*job[:2], args, *job[2:], gpu=gpu)
        finally:
            free.put(gpu)

    with ThreadPoolExecutor(args.gpus) as pool:
        return list(pool.map(on_a_free_gpu, jobs))


def view_table(rows: list[tuple[str, str, list[dict]]], most: int = 12) -> str:
    """Each held-out view's PSNR (metrics.json's ``per_image``), the mean over a row's runs, for
    the rows whose scene holds at most ``most`` views; "" when none does."""
    lines = []
    for name, setting, runs in rows:
        ok = [r for r in runs if "per_image" in r]
        if not ok or len(ok[0]["per_image"]) > most:
            continue
        views = [Path(v["image"]).stem for v in ok[0]["per_image"]]
        if not lines:
            lines = ["| scene | setting | runs | held-out views: PSNR (mean over the runs; lowest run) |", "|---|---|---:|---|"]
        cells = []
        for i, view in enumerate(views):
            scores = [r["per_image"][i]["psnr"] for r in ok]
            cells.append(f"{view} {statistics.fmean(scores):.2f}" + (f" ({min(scores):.2f})" if len(ok) > 1 else ""))
        lines.append(f"| {name} | {setting} | {len(ok)} | {', '.join(cells)} |")
    return "\n".join(lines)


def picture(run: Path, metrics: dict, height: int = 128) -> np.ndarray | None:
    """[height, 3 W, 3] uint8: the first held-out view's ground truth, render and depth, side by
    side (nearest-neighbour resized), or None without metrics."""
    if "per_image" not in metrics:
        return None
    name = Path(metrics["per_image"][0]["image"])
    truth = iio.imread(name)
    if truth.shape[-1] == 4:  # a NeRF-synthetic image, scored over white
        alpha = truth[..., 3:].astype(np.float32) / 255.0
        truth = (truth[..., :3] * alpha + 255.0 * (1.0 - alpha) + 0.5).astype(np.uint8)
    images = [truth[..., :3], iio.imread(run / "renders" / f"{name.stem}.png")[..., :3],
              iio.imread(run / "depth" / f"{name.stem}.png")]
    images[2] = np.repeat(images[2][..., None], 3, -1) if images[2].ndim == 2 else images[2][..., :3]
    width = round(height * images[0].shape[1] / images[0].shape[0])

    def resized(im: np.ndarray) -> np.ndarray:  # the ground truth is full size, a --downscale run's renders not
        rows = (np.arange(height) * im.shape[0] / height).astype(int)
        return im[rows][:, (np.arange(width) * im.shape[1] / width).astype(int)]

    return np.concatenate([resized(im) for im in images], 1)


def summary(runs: list[dict]) -> dict:
    """Mean (and sd over runs) of each column."""
    ok = [r for r in runs if "error" not in r]
    if not ok:
        return {"error": runs[0]["error"]}
    coded = "psnr_mean_code" in ok[0]
    columns = {
        "whole": [whole_psnr(r) for r in ok],
        "mean_code": [r["psnr_mean_code"] for r in ok] if coded else None,
        "right": [r["psnr"] for r in ok] if coded else None,
        "ssim": [r["ssim"] for r in ok],
        "steps": [r["steps"] for r in ok],
        "ms": [1000.0 * r["train_seconds"] / max(r["steps"], 1) for r in ok],
        "spr": [r.get("train_samples_per_ray", math.nan) for r in ok],
    }
    out = {k: None if v is None else statistics.fmean(v) for k, v in columns.items()}
    out["whole_sd"] = statistics.stdev(columns["whole"]) if len(ok) > 1 else 0.0
    used = collections.Counter(r["contraction"] for r in ok)  # a probe may choose differently from run to run
    out["contraction"] = ", ".join(k if len(used) == 1 else f"{k} ×{n}" for k, n in used.items())
    out["runs"] = len(ok)
    return out


def whole_psnr(run: dict) -> float:
    """A run's whole-image PSNR as the table's "PSNR whole" column reads it."""
    return run["psnr_nearest_code"] if "psnr_nearest_code" in run else run["psnr"]


def paired(runs: list[dict], base: list[dict]) -> dict:
    """The whole-image PSNR of ``runs`` minus that of ``base`` trained with the same seeds (the
    i-th of each), over the pairs in which both trained: mean, sd and the number of pairs."""
    deltas = [whole_psnr(r) - whole_psnr(b) for r, b in zip(runs, base) if "error" not in r and "error" not in b]
    if not deltas:
        return {"pairs": 0}
    return {"pairs": len(deltas), "delta": statistics.fmean(deltas),
            "delta_sd": statistics.stdev(deltas) if len(deltas) > 1 else 0.0}


def pair_table(rows: list[tuple[str, str, dict]]) -> str:
    """The compared settings against the defaults, seed by seed (:func:`paired`)."""
    lines = ["| scene | setting | Δ PSNR whole against the defaults, same seeds | pairs |", "|---|---|---:|---:|"]
    for name, setting, d in rows:
        delta = "" if d["pairs"] == 0 else f"{d['delta']:+.2f}" + (f" ± {d['delta_sd']:.2f}" if d["pairs"] > 1 else "")
        lines.append(f"| {name} | {setting} | {delta} | {d['pairs']} |")
    return "\n".join(lines)


def table(rows: list[tuple[str, str, dict]]) -> str:
    lines = ["| scene | setting | contraction | PSNR whole | whole, mean code | right half (fitted code) | SSIM "
             "| steps | ms/step | samples/ray | runs |", "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, setting, s in rows:
        if "error" in s:
            lines.append(f"| {name} | {setting} | failed: {s['error']} | | | | | | | | |")
            continue
        right = "" if s["right"] is None else f"{s['right']:.2f}"
        mean_code = "" if s["mean_code"] is None else f"{s['mean_code']:.2f}"
        sd = f" ± {s['whole_sd']:.2f}" if s["runs"] > 1 else ""
        lines.append(f"| {name} | {setting} | {s['contraction']} | {s['whole']:.2f}{sd} | {mean_code} | {right} "
                     f"| {s['ssim']:.4f} "
                     f"| {s['steps']:.0f} | {s['ms']:.2f} | {s['spr']:.1f} | {s['runs']} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", default=",".join(SCENES), help=f"comma-separated, of {', '.join(SCENES)}")
    parser.add_argument("--lego", type=Path, help="lego_half (NeRF-synthetic folder)")
    parser.add_argument("--fox", type=Path, help="instant-ngp's fox folder")
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--downscale", type=int, default=1, help="train and score every scene at 1/N resolution")
    parser.add_argument("--runs", type=int, default=1, help="runs per scene and setting (seeds SEED, SEED + 1, ...)")
    parser.add_argument("--seed", type=int, default=0, help="the first run's seed")
    parser.add_argument("--compare", action="append", default=[], help="KEY=VALUE[,KEY=VALUE]: also train each scene with these")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--gpus", type=int, default=1, help="CUDA: runs at once, one per GPU (0 .. N-1)")
    parser.add_argument("--out", type=Path, default=Path("bench_captures"))
    args = parser.parse_args()
    names = [n for n in args.scenes.split(",") if n]
    unknown = [n for n in names if n not in SCENES]
    if unknown:
        raise SystemExit(f"unknown scene {unknown[0]!r}; scenes: {', '.join(SCENES)}")
    if args.gpus > 1:
        if args.device != "cuda":
            raise SystemExit("--gpus N trains on CUDA GPUs (--device cuda)")
        visible = os.environ.get("CUDA_VISIBLE_DEVICES")  # a scheduler's share of the machine, if set
        args.gpu_ids = visible.split(",") if visible else [str(i) for i in range(torch.cuda.device_count())]
        if args.gpus > len(args.gpu_ids):
            raise SystemExit(f"--gpus {args.gpus}: {len(args.gpu_ids)} GPUs visible")
    args.out.mkdir(parents=True, exist_ok=True)
    settings = ["defaults", *args.compare]
    jobs = [(scene_folder(name, args.out / "scenes", args), args.out / "runs" / f"{name}-{setting}-{seed}", seed,
             [] if setting == "defaults" else setting.split(","))
            for name in names for setting in settings for seed in range(args.seed, args.seed + args.runs)]
    results = iter(train_all(jobs, args))
    rows, pairs, record, pictures, per_view = [], [], [], [], []
    for name in names:
        for setting in settings:
            runs = [next(results) for _ in range(args.runs)]
            if setting == "defaults":
                base = runs
            else:
                pairs.append((name, setting, paired(runs, base)))
            pictures.append(picture(args.out / "runs" / f"{name}-{setting}-{args.seed}", runs[0]))
            rows.append((name, setting, summary(runs)))
            per_view.append((name, setting, runs))
            record.append({"scene": name, "setting": setting, "runs": runs})
    print(f"\n{args.seconds:g} s per run on {args.device}\n" + table(rows))
    if pairs:
        print("\n" + pair_table(pairs))
    views = view_table(per_view)
    if views:
        print("\n" + views)
    shown = [p for p in pictures if p is not None]
    if shown:  # one row per scene and setting: ground truth, render, depth of the first held-out view
        width = max(p.shape[1] for p in shown)
        iio.imwrite(args.out / "captures.png", np.concatenate([np.pad(p, ((0, 0), (0, width - p.shape[1]), (0, 0)))
                                                               for p in shown]))
    (args.out / "captures.json").write_text(json.dumps({"seconds": args.seconds, "device": args.device,
                                                        "rows": record}, indent=1))


if __name__ == "__main__":
    main()
