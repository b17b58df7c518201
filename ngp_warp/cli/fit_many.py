"""``ngp-warp fit-many MANIFEST --out DIR``: one radiance field per scene of a list.

MANIFEST is a text file naming scene folders, one a line (relative to the file; blank lines and
``#`` comments are skipped; a line may be a glob), or a glob itself. Under torchrun (or with
``--gpus N``) the scenes are handed out as ranks free up: each rank claims the next scene from a
counter in the process group's store, so a slow scene does not leave another rank idle. The
largest scenes (bytes on disk) are handed out first, so that the last to finish are small ones
and the ranks end close together. Each rank
trains its scenes one at a time, on its own GPU or as a CPU process, through the ``train``
command's path, into ``DIR/<scene folder name>/`` (checkpoint, metrics.json, renders, ...). A
scene whose metrics.json is complete is skipped; one with a checkpoint resumes with what is left
of the budget. Rank 0 then writes ``DIR/summary.json`` (each scene's row, with the rank that fit
it, and each rank's busy and idle seconds) and prints the table (PSNR, time per scene).
"""

from __future__ import annotations

import argparse
import glob
import json
import sys
import threading
import time
from pathlib import Path

from ngp_warp.cli.common import CHECKPOINT, UserError, check_run_apart, train_and_report, train_config, writable_dir
from ngp_warp.data.data_error import DataError

SUMMARY = "summary.json"
QUEUE_KEY = "ngp-warp/fit-many/next-scene"
RESULT_KEY = "ngp-warp/fit-many/result/"  # + rank: that rank's rows and busy seconds, as JSON
ALIVE_KEY = "ngp-warp/fit-many/alive/"  # + rank: a counter the rank raises every HEARTBEAT_SECONDS
HEARTBEAT_SECONDS = 2.0
LOST_AFTER_SECONDS = 60.0  # rank 0 takes a rank whose counter stood still this long for dead
METRICS_KEYS = ("psnr", "steps", "train_seconds", "n_test_images", "per_image")


class FitManyError(DataError):
    """A manifest that names no usable scene folders, a bad option, or scenes that failed; one
    line. A DataError, which the CLI reports also when run as ``python -m ngp_warp.cli`` (as
    the ranks run it), where the CLI's own error class is another one."""


def _expand(pattern: str, base: Path) -> list[Path]:
    path = Path(pattern).expanduser()
    path = path if path.is_absolute() else base / path
    if glob.has_magic(pattern):
        return sorted(Path(p) for p in glob.glob(str(path)) if Path(p).is_dir())
    return [path]


def read_manifest(manifest: str) -> list[Path]:
    """The scene folders MANIFEST names, in its order (a glob: sorted). Raises FitManyError for a
    missing manifest, a named folder that does not exist, no scenes, or two scenes with one
    folder name (their run folders would collide)."""
    if Path(manifest).is_file():
        try:
            lines = Path(manifest).read_text().splitlines()
        except (OSError, UnicodeDecodeError) as e:
            raise FitManyError(f"{manifest}: unreadable manifest ({e})") from None
        base = Path(manifest).resolve().parent
        items = [line.strip() for line in lines if line.strip() and not line.strip().startswith("#")]
        scenes = [p for item in items for p in _expand(item, base)]
    elif glob.has_magic(manifest):
        scenes = _expand(manifest, Path.cwd())
    else:
        raise FitManyError(f"{manifest}: no such manifest file (a text file of scene folders, or a glob)")
    missing = [str(p) for p in scenes if not p.is_dir()]
    if missing:
        raise FitManyError(f"{manifest}: scene folder {missing[0]} does not exist")
    if not scenes:
        raise FitManyError(f"{manifest}: names no scene folders")
    names = [p.name for p in scenes]
    twice = next((n for n in names if names.count(n) > 1), None)
    if twice is not None:
        raise FitManyError(f"{manifest}: two scenes are named {twice!r} (their run folders would be one)")
    return scenes


def finished_metrics(run_dir: Path) -> dict | None:
    """The metrics of a finished run in ``run_dir``: metrics.json with every key and one score
    per test image; None otherwise."""
    try:
        metrics = json.loads((run_dir / "metrics.json").read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(metrics, dict) or any(k not in metrics for k in METRICS_KEYS):
        return None
    return metrics if len(metrics["per_image"]) == metrics["n_test_images"] > 0 else None


def remaining_budget(args, checkpoint: Path) -> tuple[int | None, float | None]:
    """(steps, seconds) left of the command line's budget after the run saved in ``checkpoint``."""
    from ngp_warp.training.checkpoint import read_checkpoint
    from ngp_warp.training.config import TrainConfig

    state = read_checkpoint(checkpoint)
    steps, seconds = TrainConfig(steps=args.steps, seconds=args.seconds).budget()
    return (None if steps is None else max(0, steps - state["step"]),
            None if seconds is None else max(0.0, seconds - state["train_seconds"]))


def fit_scene(scene: Path, run_dir: Path, args) -> dict:
    """Train, evaluate and render one scene into ``run_dir`` (skipped when finished, resumed
    from its checkpoint); its row of the summary. A user mistake in the scene is one printed
    line and a ``failed`` row."""
    from ngp_warp.training.checkpoint import CheckpointError
    from ngp_warp.data.loading import DataError
    from ngp_warp.training.run_folder import RunFolderError

    row = {"scene": scene.name, "path": str(scene), "run": str(run_dir)}
    metrics = finished_metrics(run_dir)
    if metrics is not None:
        return {**row, "status": "skipped", **_scores(metrics), "wall_seconds": None}
    start = time.perf_counter()
    resume = (run_dir / CHECKPOINT).is_file()
    try:
        options = argparse.Namespace(**{**vars(args), "resume": resume, "overwrite": args.overwrite and not resume})
        if resume:
            options.steps, options.seconds = remaining_budget(args, run_dir / CHECKPOINT)
        metrics = train_and_report(scene, run_dir, options, config=None if resume else train_config(args))
    except (UserError, DataError, CheckpointError, RunFolderError) as e:
        print(f"ngp-warp: error: {scene.name}: {e}", file=sys.stderr)
        return {**row, "status": "failed", "error": str(e), "wall_seconds": time.perf_counter() - start}
    status = "resumed" if resume else "trained"
    return {**row, "status": status, **_scores(metrics), "wall_seconds": time.perf_counter() - start}


def _scores(metrics: dict) -> dict:
    return {k: metrics[k] for k in ("psnr", "ssim", "steps", "train_seconds")}


def summary_table(rows: list[dict]) -> str:
    """The summary as text: one line per scene, then the totals."""
    lines = [f"{'scene':<24} {'status':<8} {'PSNR':>7} {'steps':>7} {'train s':>8} {'wall s':>8}"]
    for r in rows:
        psnr = "-" if r.get("psnr") is None else f"{r['psnr']:.2f}"
        steps = "-" if r.get("steps") is None else str(r["steps"])
        train = "-" if r.get("train_seconds") is None else f"{r['train_seconds']:.1f}"
        wall = "-" if r.get("wall_seconds") is None else f"{r['wall_seconds']:.1f}"
        lines.append(f"{r['scene'][:24]:<24} {r['status']:<8} {psnr:>7} {steps:>7} {train:>8} {wall:>8}")
    return "\n".join(lines)


def scene_bytes(scene: Path) -> int:
    """The bytes of the files under ``scene``: what a scene costs to load, train on and evaluate,
    as far as one can tell before loading it."""
    return sum(f.stat().st_size for f in scene.rglob("*") if f.is_file())


def largest_first(scenes: list[Path]) -> list[int]:
    """The scenes' indices, largest (:func:`scene_bytes`) first, ties in manifest order: the order
    in which the ranks claim them."""
    sizes = [scene_bytes(s) for s in scenes]
    return sorted(range(len(scenes)), key=lambda i: -sizes[i])


def claimed_scenes(order: list[int]):
    """The indices of the scenes this rank fits, in ``order``, each claimed when the rank is
    free: the next value of a counter in the process group's store picks the next of ``order``
    (every scene once over all ranks), or all of them outside a process group."""
    import torch.distributed as dist

    if not (dist.is_available() and dist.is_initialized()):
        yield from order
        return
    store = dist.distributed_c10d._get_default_store()  # the process group's store, shared by the ranks
    while (claim := _stored(store.add, QUEUE_KEY, 1) - 1) < len(order):
        yield order[claim]


def _stored(call, *args):
    """``call(*args)``, a call of the process group's store; a lost store (the node holding it
    died) as one line."""
    try:
        return call(*args)
    except RuntimeError as e:  # torch.distributed's store errors (DistNetworkError, DistStoreError, ...)
        raise FitManyError(f"lost the rendezvous store ({str(e).splitlines()[0] if str(e) else type(e).__name__}: "
                           f"its node died?); the scenes finished are kept, and the same command run again fits "
                           f"the rest") from None


class Heartbeat:
    """In its ``with`` block, a thread raises this rank's counter in the process group's store
    every :data:`HEARTBEAT_SECONDS` (nothing outside a process group), so that rank 0 can tell a
    rank still training a long scene from one whose node died."""

    def __init__(self):
        import torch.distributed as dist

        self._store = None
        if dist.is_available() and dist.is_initialized():
            self._store = dist.distributed_c10d._get_default_store()
            self._key = f"{ALIVE_KEY}{dist.get_rank()}"
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, daemon=True)

    def _beat(self) -> None:
        while not self._stop.wait(HEARTBEAT_SECONDS):
            try:
                self._store.add(self._key, 1)
            except RuntimeError:  # the store is gone: the next claim of a scene says so
                return

    def __enter__(self) -> Heartbeat:
        if self._store is not None:
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()


def _all_ranks(rows: list[dict], busy: float) -> tuple[list[dict], list[float | None], list[int]]:
    """(rows, busy seconds per rank, lost ranks). Outside a process group: this process's own.
    In one, every rank posts its rows to the store; rank 0 collects them, waiting for each rank
    until it posts or its heartbeat stands still for :data:`LOST_AFTER_SECONDS` (its node died:
    lost, busy None); other ranks return their own rows at once."""
    import torch.distributed as dist

    if not (dist.is_available() and dist.is_initialized()):
        return rows, [busy], []
    store, rank, world = dist.distributed_c10d._get_default_store(), dist.get_rank(), dist.get_world_size()
    _stored(store.set, f"{RESULT_KEY}{rank}", json.dumps([rows, busy]))
    if rank != 0:
        return rows, [busy], []
    posted, lost, beats = {}, [], {}
    while len(posted) + len(lost) < world:
        for k in sorted(set(range(world)) - set(posted) - set(lost)):
            if _stored(store.check, [f"{RESULT_KEY}{k}"]):
                posted[k] = json.loads(_stored(store.get, f"{RESULT_KEY}{k}"))
                continue
            beat, now = _stored(store.add, f"{ALIVE_KEY}{k}", 0), time.monotonic()  # read without waiting
            if beats.get(k, (None,))[0] != beat:
                beats[k] = (beat, now)
            elif now - beats[k][1] > LOST_AFTER_SECONDS:
                lost.append(k)
        time.sleep(0.2)
    return ([row for k in sorted(posted) for row in posted[k][0]],
            [posted[k][1] if k in posted else None for k in range(world)], sorted(lost))


def cmd_fit_many(args) -> None:
    from ngp_warp.atomic import atomic_write_text
    from ngp_warp.training.distributed import FIT_MANY_TIMEOUT, is_main_rank, join, rank_and_size
    from ngp_warp.training.rank_env import started_as_rank

    scenes = read_manifest(args.manifest)  # bad input: one line before anything is written
    try:
        for scene in scenes:
            check_run_apart(Path(args.out) / scene.name, scene)
        train_config(args)
        out = writable_dir(Path(args.out))
    except UserError as e:
        raise FitManyError(str(e)) from None
    if started_as_rank():  # coordination only: gloo, also between GPUs
        args.device = join(args.device, backend="gloo", timeout=FIT_MANY_TIMEOUT)
    rank, world = rank_and_size()
    args.quiet = args.quiet or rank != 0  # one rank's progress bars on the terminal
    start = time.perf_counter()
    with Heartbeat():
        rows = [{**fit_scene(scenes[i], out / scenes[i].name, args), "rank": rank}
                for i in claimed_scenes(largest_first(scenes))]
    busy = time.perf_counter() - start
    rows, busy_per_rank, lost = _all_ranks(rows, busy)
    rows = sorted(rows, key=lambda r: [s.name for s in scenes].index(r["scene"]))
    wall = time.perf_counter() - start
    fitted = sum(r["status"] in ("trained", "resumed") for r in rows)
    failed = [r["scene"] for r in rows if r["status"] == "failed"]
    if is_main_rank():
        per_rank = [{"rank": k, "scenes": sum(r["rank"] == k for r in rows), "busy_seconds": b,
                     "idle_seconds": None if b is None else wall - b, "lost": k in lost}
                    for k, b in enumerate(busy_per_rank)]
        summary = {"ranks": world, "wall_seconds": wall, "scenes_per_hour": 3600.0 * fitted / wall,
                   "per_rank": per_rank, "scenes": rows}
        atomic_write_text(out / SUMMARY, json.dumps(summary, indent=2))
        print(summary_table(rows))
        idle = ", ".join(f"rank {r['rank']} " + ("lost" if r["lost"] else f"{r['idle_seconds']:.1f} s")
                         for r in per_rank)
        print(f"{len(rows)} scenes ({fitted} fitted, {len(rows) - fitted - len(failed)} skipped as finished, "
              f"{len(failed)} failed) on {world} rank(s) in {wall:.1f} s (idle: {idle}); wrote {out / SUMMARY}")
    if lost:
        raise FitManyError(f"rank(s) {', '.join(map(str, lost))} stopped answering (no heartbeat for "
                           f"{LOST_AFTER_SECONDS:.0f} s: a node died?); the scenes finished are kept, and the same "
                           f"command run again fits the rest")
    if failed and is_main_rank():  # rank 0 reports every rank's rows; the others end as it does
        raise FitManyError(f"{len(failed)} of {len(rows)} scenes failed: {', '.join(failed)} (see {out / SUMMARY})")


def add_fit_many_parser(sub, training, common, folder, positive_int) -> argparse.ArgumentParser:
    """The ``fit-many`` subcommand, with the ``train`` command's training options (``training``,
    ``common``: the CLI's option groups; ``folder``, ``positive_int``: its argument types)."""
    f = sub.add_parser("fit-many", help="train one field per scene of a manifest, scenes spread over ranks")
    f.add_argument("manifest", help="text file of scene folders (one a line, relative to it) or a glob")
    f.add_argument("--out", type=folder, required=True, help="output folder: one run folder per scene")
    f.add_argument("--gpus", type=positive_int, default=1, help="ranks on this machine, one GPU each (docs/multi-gpu.md)")
    training(f)
    common(f)
    f.set_defaults(func=cmd_fit_many)
    return f
