"""The ``ngp-warp`` command: train, eval, render, bench, demo."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

CHECKPOINT = "checkpoint.pt"


class UserError(Exception):
    """A mistake in the command line or its inputs: reported as one line, no traceback."""


def _device(name: str | None) -> str:
    from ngp_warp import _wp
    from ngp_warp.config import default_device

    if name in (None, "auto"):
        return default_device()
    if name.startswith("cuda") and not _wp.cuda_available():
        raise UserError(f"--device {name}: no CUDA GPU usable by torch and Warp on this machine (use --device cpu)")
    if name != "cpu" and not name.startswith("cuda"):
        raise UserError(f"--device {name}: expected cpu, cuda or cuda:N")
    return name


def _writable_dir(path: Path) -> Path:
    """Create ``path`` if needed and prove we can write there, before any long work starts."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / f".ngp-warp-write-test-{os.getpid()}"  # data-parallel ranks probe at once
        probe.write_text("")
        probe.unlink()
    except OSError as e:
        raise UserError(f"{path}: output folder is not writable ({e.strerror or e})") from None
    return path


def _with_settings(cfg, args):
    """``cfg`` with ``--target-samples`` and the ``--set KEY=VALUE`` settings applied."""
    from ngp_warp.config import apply_overrides

    if args.target_samples:
        cfg.target_samples = args.target_samples
    try:
        cfg = apply_overrides(cfg, args.set)
        cfg.check()
        return cfg
    except ValueError as e:
        raise UserError(f"--set: {e}") from None


def _train_config(args):
    from ngp_warp.config import TrainConfig

    return _with_settings(TrainConfig(steps=args.steps, seconds=args.seconds, seed=args.seed), args)


def _train_and_report(scene_path: Path, out: Path, args, config=None) -> dict:
    """Train (or resume), checkpoint, evaluate and render into ``out``."""
    from ngp_warp.data import load_scene

    device = _device(args.device)
    out = Path(out)
    resume = getattr(args, "resume", False)
    scene = None if resume else load_scene(scene_path, downscale=args.downscale)
    created = not out.exists()
    out = _writable_dir(out)
    try:
        return _run(scene, scene_path, out, args, device, config, resume)
    except BaseException:
        if created and not any(out.iterdir()):
            out.rmdir()  # leave nothing behind for a run that wrote nothing
        raise


def _run(scene, scene_path: Path, out: Path, args, device: str, config, resume: bool) -> dict:
    from ngp_warp.checkpoint import load_trainer, save_checkpoint
    from ngp_warp.evaluate import evaluate, render_orbit
    from ngp_warp.trainer import Trainer

    ckpt = out / CHECKPOINT
    downscale = args.downscale
    if resume:
        trainer, record = load_trainer(ckpt, device=device)
        trainer.config.steps, trainer.config.seconds = args.steps, args.seconds
        scene_path, downscale = Path(record["path"]), record["downscale"]  # what the run trained on
        print(f"resuming from {ckpt} at step {trainer.step_count}", file=sys.stderr)
    else:
        trainer = Trainer(scene, config, device=device)
    if getattr(args, "data_parallel", False):  # rank 0 alone reports, saves and evaluates
        from ngp_warp.distributed import is_main_rank, make_data_parallel

        make_data_parallel(trainer)
        if not is_main_rank():
            return trainer.train(show_progress=False)
    scene = trainer.scene
    print(f"scene {scene_path} ({scene.source}): {len(scene.train.names)} train views "
          f"{scene.train.width}x{scene.train.height}, device {trainer.device}, finest hash-grid "
          f"level {trainer.config.field.finest_resolution:g} cells, table 2^{trainer.config.field.log2_hashmap_size} "
          f"per level, distortion loss weight {trainer.config.distortion_weight:g}, "
          f"{trainer.config.supersample}x{trainer.config.supersample} rays per pixel", file=sys.stderr)
    if scene.test_is_heldout:
        print(f"no test split: evaluating on {len(scene.test.names)} frames held out of training",
              file=sys.stderr)
    try:
        trainer.train(show_progress=not args.quiet)
    except KeyboardInterrupt:
        save_checkpoint(trainer, ckpt, scene_path, downscale)
        print(f"ngp-warp: interrupted at step {trainer.step_count}; checkpoint saved to {ckpt} "
              f"(continue with --resume)", file=sys.stderr)
        raise
    save_checkpoint(trainer, ckpt, scene_path, downscale)
    metrics = evaluate(trainer, out, show_progress=not args.quiet)
    if not args.no_video:
        video = render_orbit(trainer, out / "orbit.mp4", n_frames=args.frames, show_progress=not args.quiet)
        print(f"orbit video: {video}", file=sys.stderr)
    return metrics


def _print_metrics(metrics: dict, out: Path) -> None:
    ssim = "n/a (images under 11 px)" if metrics["ssim"] is None else f"{metrics['ssim']:.4f}"
    print(f"{metrics['test_split']}: PSNR {metrics['psnr']:.2f} dB  SSIM {ssim}  "
          f"({metrics['n_test_images']} images, {metrics['steps']} steps, "
          f"{metrics['train_seconds']:.1f} s training on {metrics['device']})")
    print(f"wrote {out / 'metrics.json'}, {out / 'renders'}/, {out / 'depth'}/, {out / CHECKPOINT}")


def cmd_train(args) -> None:
    scene = Path(args.scene)
    if args.resume and args.set:
        raise UserError("--set with --resume: a resumed run keeps the settings in its checkpoint")
    config = None if args.resume else _train_config(args)  # bad settings fail before any loading
    from ngp_warp.distributed import join_data_parallel

    args.data_parallel = join_data_parallel(args)  # under torchrun: this rank's device in args.device
    metrics = _train_and_report(scene, Path(args.out), args, config=config)
    if metrics is not None:  # None on ranks other than 0
        _print_metrics(metrics, Path(args.out))


def demo_config(device: str, steps: int | None, seconds: float | None, seed: int):
    """Training settings for the 100×100 demo scene. On the CPU a smaller table, a coarser
    occupancy grid and a longer step keep 2 cores busy on useful samples; the finest hash-grid
    level follows the images (104 cells here; measured on 2 cores after 150 s: 33.8 dB, against
    32.7 dB with 512 cells, see benchmarks/RESULTS.md)."""
    from ngp_warp.config import TrainConfig
    from ngp_warp.field import FieldConfig

    if steps is None and seconds is None:
        seconds = 150.0 if device == "cpu" else 30.0
    if device == "cpu":
        return TrainConfig(steps=steps, seconds=seconds, seed=seed, target_samples=1 << 13,
                           grid_resolution=64, steps_per_diagonal=512,
                           field=FieldConfig(log2_hashmap_size=16))
    return TrainConfig(steps=steps, seconds=seconds, seed=seed)


def cmd_demo(args) -> None:
    from ngp_warp.scene import write_demo_scene

    out = _writable_dir(Path(args.out))
    scene_dir = out / "scene"
    if not (scene_dir / "transforms_train.json").exists():
        print(f"generating the demo scene in {scene_dir}", file=sys.stderr)
        write_demo_scene(scene_dir, seed=args.seed)
    config = _with_settings(demo_config(_device(args.device), args.steps, args.seconds, args.seed), args)
    metrics = _train_and_report(scene_dir, out, args, config=config)
    _print_metrics(metrics, out)


def cmd_eval(args) -> None:
    from ngp_warp.checkpoint import load_trainer
    from ngp_warp.evaluate import evaluate

    trainer, _ = load_trainer(Path(args.dir) / CHECKPOINT, device=_device(args.device), scene_path=args.scene)
    out = _writable_dir(Path(args.dir))
    _print_metrics(evaluate(trainer, out, show_progress=not args.quiet), out)


def cmd_render(args) -> None:
    from ngp_warp.checkpoint import load_trainer
    from ngp_warp.evaluate import render_orbit

    video = Path(args.video)
    if video.suffix.lower() not in (".mp4", ".gif"):
        raise UserError(f"--video {video}: expected a .mp4 or .gif path")
    trainer, _ = load_trainer(Path(args.dir) / CHECKPOINT, device=_device(args.device), scene_path=args.scene)
    out = _writable_dir(Path(args.dir))
    if not video.is_absolute():
        video = out / video
    if not video.parent.is_dir():
        raise UserError(f"--video {video}: folder {video.parent} does not exist")
    written = render_orbit(trainer, video, n_frames=args.frames, show_progress=not args.quiet)
    print(f"wrote {written}")


def cmd_bench(args) -> None:
    from ngp_warp.bench import run_kernel_bench

    run_kernel_bench(_device(args.device), quick=args.quick)


def _positive(kind):
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a positive {kind.__name__}, got {text!r}") from None
        if not value > 0:
            raise argparse.ArgumentTypeError(f"expected a positive {kind.__name__}, got {text!r}")
        return value

    parse.__name__ = kind.__name__
    return parse


def _parser() -> argparse.ArgumentParser:
    from ngp_warp.fit_many import add_fit_many_parser

    p = argparse.ArgumentParser(prog="ngp-warp", description="instant-NGP radiance fields on Warp kernels (CPU or CUDA)")
    sub = p.add_subparsers(dest="command", required=True)

    def common(sp):
        sp.add_argument("--device", default="auto", help="cpu, cuda or cuda:N (default: cuda when present)")
        sp.add_argument("--quiet", action="store_true", help="no progress bars")

    def training(sp):
        budget = sp.add_mutually_exclusive_group()
        budget.add_argument("--steps", type=_positive(int), help="training steps")
        budget.add_argument("--seconds", type=_positive(float), help="training wall-clock budget in seconds")
        sp.add_argument("--downscale", type=_positive(int), default=1, help="shrink images by this integer factor")
        sp.add_argument("--seed", type=int, default=0)
        sp.add_argument("--target-samples", type=_positive(int), help="samples per batch (default 2^18 CUDA, 2^15 CPU)")
        sp.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="any training setting, e.g. distortion_weight=0 or field.log2_hashmap_size=19 "
                             "(repeatable; see ngp_warp.config.TrainConfig)")
        sp.add_argument("--no-video", action="store_true", help="skip the orbit video")
        sp.add_argument("--frames", type=_positive(int), default=60, help="orbit video frames")

    t = sub.add_parser("train", help="train on a scene folder, then evaluate and render")
    t.add_argument("scene", help="NeRF-synthetic folder or folder with an instant-ngp transforms.json")
    t.add_argument("--out", required=True, help="output folder")
    t.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    t.add_argument("--gpus", type=_positive(int), default=1, help="data-parallel ranks through torchrun (README)")
    training(t)
    common(t)
    t.set_defaults(func=cmd_train)

    d = sub.add_parser("demo", help="generate the built-in procedural scene, train and evaluate on it")
    d.add_argument("--out", default="ngp-warp-demo", help="output folder (default ./ngp-warp-demo)")
    training(d)
    common(d)
    d.set_defaults(func=cmd_demo)

    e = sub.add_parser("eval", help="evaluate a trained output folder on its test split")
    e.add_argument("dir")
    e.add_argument("--scene", help="scene folder, if it moved since training")
    common(e)
    e.set_defaults(func=cmd_eval)

    r = sub.add_parser("render", help="render an orbit video from a trained output folder")
    r.add_argument("dir")
    r.add_argument("--video", default="orbit.mp4", help="video path (.mp4, or .gif; relative to DIR)")
    r.add_argument("--frames", type=_positive(int), default=60)
    r.add_argument("--scene", help="scene folder, if it moved since training")
    common(r)
    r.set_defaults(func=cmd_render)

    add_fit_many_parser(sub, training, common, str, _positive(int))

    b = sub.add_parser("bench", help="kernel throughput table")
    b.add_argument("--quick", action="store_true", help="small sizes only")
    common(b)
    b.set_defaults(func=cmd_bench)
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if getattr(args, "gpus", 1) > 1:  # run this command line as that many torchrun ranks
        from ngp_warp.distributed import launch_ranks

        return launch_ranks(args, sys.argv[1:] if argv is None else argv)
    from ngp_warp.checkpoint import CheckpointError
    from ngp_warp.data import DataError

    try:
        args.func(args)
    except (UserError, DataError, CheckpointError) as e:
        print(f"ngp-warp: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("ngp-warp: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
