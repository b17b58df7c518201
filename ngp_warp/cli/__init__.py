"""The ``ngp-warp`` command: train, eval, render, export, view, process, fit-many, bench, demo,
one module per subcommand, and the one error boundary (:func:`main`). The library never imports
this package."""

from __future__ import annotations

import argparse
import contextlib
import io
import logging
import os
import sys
from typing import NoReturn

from ngp_warp import _interrupt_while_loading, cuda_start
from ngp_warp.cli import ranks
from ngp_warp.cli.train import prefetch_scene_images
from ngp_warp.training import rank_env
from ngp_warp.cli.common import CHECKPOINT, MAX_DOWNSCALE, UserError, folder_name, positive, seed_number
from ngp_warp.wall_clock import command_started

__all__ = ["CHECKPOINT", "UserError", "main", "run"]


def _common(sp: argparse.ArgumentParser) -> None:
    """The device and quiet options most subcommands take."""
    sp.add_argument("--device", default="auto", help="cpu, cuda or cuda:N (default: cuda when present)")
    sp.add_argument("--quiet", action="store_true", help="no progress bars")


def _training(sp: argparse.ArgumentParser) -> None:
    """The options of the subcommands that train."""
    from ngp_warp.outputs.camera_path import MAX_FRAMES

    budget = sp.add_mutually_exclusive_group()
    budget.add_argument("--steps", type=positive(int), help="training steps (with --resume: this many more)")
    budget.add_argument("--seconds", type=positive(float),
                        help="training wall-clock budget in seconds (with --resume: this many more)")
    sp.add_argument("--downscale", type=positive(int, high=MAX_DOWNSCALE), help="shrink images by this integer factor (default 1)")
    sp.add_argument("--seed", type=seed_number, help="random seed of the training (and of the demo's scene; default 0)")
    sp.add_argument("--target-samples", type=positive(int), help="samples per batch (default 2^18 CUDA, 2^15 CPU)")
    sp.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="any training setting, e.g. distortion_weight=0 or field.log2_hashmap_size=19 "
                         "(repeatable; see ngp_warp.training.config.TrainConfig)")
    sp.add_argument("--no-video", action="store_true", help="skip the orbit video")
    sp.add_argument("--frames", type=positive(int, high=MAX_FRAMES), default=60, help="orbit video frames")
    sp.add_argument("--overwrite", action="store_true", help="replace the run already in the output folder")
    sp.add_argument("--checkpoint-every", type=positive(float), default=300.0, metavar="SECONDS",
                    help="save a checkpoint this often while training (default 300; also on Ctrl-C and SIGTERM)")


def _parser() -> argparse.ArgumentParser:
    """The whole command line (loading every subcommand's modules: torch and Warp among them)."""
    from ngp_warp.cli.bench import cmd_bench
    from ngp_warp.cli.evaluate import cmd_eval
    from ngp_warp.cli.export import add_export_parser
    from ngp_warp.cli.fit_many import add_fit_many_parser
    from ngp_warp.cli.process import add_process_parser
    from ngp_warp.cli.render import add_path_arguments, cmd_render
    from ngp_warp.cli.train import cmd_demo, cmd_train
    from ngp_warp.cli.view import add_view_parser

    p = argparse.ArgumentParser(prog="ngp-warp", description="instant-NGP radiance fields on Warp kernels (CPU or CUDA)")
    sub = p.add_subparsers(dest="command", required=True)

    t = sub.add_parser("train", help="train on a scene folder, then evaluate and render")
    t.add_argument("scene", help="scene folder (NeRF-synthetic, an instant-ngp transforms.json, or a COLMAP "
                                 "model in sparse/0/ beside images/) or a transforms file")
    t.add_argument("--out", type=folder_name, required=True, help="output folder")
    t.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    t.add_argument("--gpus", type=positive(int), default=1, help="data-parallel ranks on this machine, one GPU each (docs/multi-gpu.md)")
    _training(t)
    _common(t)
    t.set_defaults(func=cmd_train)

    d = sub.add_parser("demo", help="generate the built-in procedural scene, train and evaluate on it")
    d.add_argument("--out", type=folder_name, default="ngp-warp-demo", help="output folder (default ./ngp-warp-demo)")
    d.add_argument("--scene", choices=("demo", "unbounded"), default="demo",  # ngp_warp.training.demo.DEMOS
                   help="demo: objects in a box, white background; unbounded: the 360° scene (objects "
                        "on a ground plane to the horizon, learned background, contracted space)")
    _training(d)
    _common(d)
    d.set_defaults(func=cmd_demo)

    e = sub.add_parser("eval", help="evaluate a trained output folder on its test split")
    e.add_argument("dir", type=folder_name, help="a trained output folder (holding checkpoint.pt)")
    e.add_argument("--scene", help="scene folder, if it moved since training")
    _common(e)
    e.set_defaults(func=cmd_eval)

    r = sub.add_parser("render", help="render a video along a camera path from a trained output folder")
    r.add_argument("dir", type=folder_name, help="a trained output folder (holding checkpoint.pt)")
    r.add_argument("--video", default="orbit.mp4", help="video path (.mp4, or .gif; relative to DIR)")
    add_path_arguments(r)
    r.add_argument("--scene", help="scene folder, if it moved since training")
    r.add_argument("--near", type=positive(float), metavar="D",
                   help="rays start D from their camera, in the scene's lengths (default: where training's "
                        "started; a path closer to the subject than the training cameras needs less)")
    _common(r)
    r.set_defaults(func=cmd_render)

    _common(add_export_parser(sub, positive(int), positive(float)))
    _common(add_view_parser(sub))
    add_process_parser(sub)

    add_fit_many_parser(sub, _training, _common, folder_name, positive(int))

    b = sub.add_parser("bench", help="kernel throughput table")
    b.add_argument("--quick", action="store_true", help="small sizes only")
    _common(b)
    b.set_defaults(func=cmd_bench)
    return p


def main(argv: list[str] | None = None) -> int:
    started = command_started()
    argv = sys.argv[1:] if argv is None else list(argv)
    asked = ranks.ranks_asked(argv)
    if 1 < asked <= (os.cpu_count() or 1) and not rank_env.started_as_rank():  # before anything heavy loads
        return ranks.launch(asked, ranks.without_gpus(argv))
    if asked <= 1 or rank_env.started_as_rank():  # torch's import goes on beside these; a launcher uses no GPU
        if argv[:1] == ["train"] and not rank_env.started_as_rank():  # ranks would share the cores and /dev/shm
            prefetch_scene_images(argv[1:])  # the child first, while this process has one thread
        cuda_start.start_cuda(argv)
    with _interrupt_while_loading():
        parser = _parser()
    args = _parse(parser, argv)
    args.started = started
    if getattr(args, "gpus", 1) > 1:
        if rank_env.started_as_rank():
            error = "torchrun already started the ranks (drop --gpus)"
        elif (error := _ranks_do_not_fit(args, args.gpus)) is None:  # more GPUs than cores
            return ranks.launch(args.gpus, ranks.without_gpus(argv))
        print(f"ngp-warp: error: --gpus {args.gpus}: {error}", file=sys.stderr)
        return 2
    if rank_env.started_as_rank():
        n = int(os.environ.get("LOCAL_WORLD_SIZE", os.environ["WORLD_SIZE"]))
        if (error := _ranks_do_not_fit(args, n)) is not None:
            if rank_env.reports():
                print(f"ngp-warp: error: --gpus {n}: {error}", file=sys.stderr)
            return 2
    with _interrupt_while_loading():
        from ngp_warp.training.checkpoint import CheckpointError
        from ngp_warp.data.loading import DataError
        from ngp_warp.training.memory_estimate import SettingsTooLarge
        from ngp_warp.training.run_folder import SIGTERM_EXIT, RunFolderError, Terminated, sigterm_as_interrupt

    try:
        with sigterm_as_interrupt():
            args.func(args)
    except (UserError, DataError, CheckpointError, RunFolderError, SettingsTooLarge) as e:
        print(f"ngp-warp: error: {e}", file=sys.stderr)
        return 2
    except Terminated:
        if rank_env.reports():  # of several ranks, the first of each machine
            print("ngp-warp: terminated (SIGTERM)", file=sys.stderr)
        return SIGTERM_EXIT
    except KeyboardInterrupt:
        if rank_env.reports():
            print("ngp-warp: interrupted", file=sys.stderr)
        return 130
    return 0


def run() -> NoReturn:
    """The ``ngp-warp`` program (and ``python -m ngp_warp.cli``): :func:`main`, then the process
    ends at once, its output flushed. Every file the command writes is closed and its threads
    joined when :func:`main` returns; what the interpreter's own teardown would add (freeing
    torch and Warp: 0.6 s a command on 2 CPU cores) serves nothing. An exception out of
    :func:`main` (a bug) still ends the usual way, with its traceback."""
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    logging.shutdown()
    os._exit(code)


def _parse(parser: argparse.ArgumentParser, argv: list[str]) -> argparse.Namespace:
    """``parser.parse_args(argv)``; a rank that does not report
    (:func:`~ngp_warp.training.rank_env.reports`) exits as the parser does (code 2, or 0 for
    ``--help``) but silently: another reports what every rank parses alike."""
    if rank_env.reports():
        return parser.parse_args(argv)
    with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
        return parser.parse_args(argv)


def _ranks_do_not_fit(args: argparse.Namespace, n: int) -> str | None:
    """Why this machine cannot hold ``n`` ranks (one GPU each, or one CPU core each with
    ``--device cpu``), or None."""
    import torch

    if getattr(args, "device", "auto") != "cpu":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count < n:
            return f"this machine has {count} CUDA GPU(s) (with --device cpu: {n} CPU processes)"
    elif n > (os.cpu_count() or 1):
        return f"this machine has {os.cpu_count() or 1} CPU cores, too few for {n} CPU processes"
    return None
