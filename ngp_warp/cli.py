"""The ``ngp-warp`` command: train, eval, render, export, view, process, fit-many, bench, demo."""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

CHECKPOINT = "checkpoint.pt"
ORBIT_FPS = 20.0  # the training run's orbit video


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


def _train_config(args, device: str | None = None):  # device: resolved already, else args.device's
    from ngp_warp.config import TrainConfig, cpu_sizes
    cfg = TrainConfig(steps=args.steps, seconds=args.seconds, seed=args.seed)
    return _with_settings(cpu_sizes(cfg) if (device or _device(args.device)) == "cpu" else cfg, args)  # --set wins


def new_trainer(scene, config, device: str):
    """A Trainer; its ValueErrors, which name a setting that does not suit the scene, as UserError."""
    from ngp_warp.trainer import Trainer
    try:
        return Trainer(scene, config, device=device)
    except ValueError as e:
        raise UserError(f"--set: {e}") from None


def _train_and_report(scene_path: Path, out: Path, args, config=None) -> dict:
    """Train (or resume), checkpoint, evaluate and render into ``out`` (a folder of one run:
    :class:`ngp_warp.run_folder.RunFolder`)."""
    from ngp_warp.data import load_scene
    from ngp_warp.run_folder import RunFolder

    device = _device(args.device)
    out = Path(out)
    resume = getattr(args, "resume", False)
    folder = RunFolder(out, resume, args.overwrite, ("--resume" if hasattr(args, "resume") else None, "--overwrite"))
    scene = None if resume else load_scene(scene_path, downscale=args.downscale or 1)
    created = not out.exists()
    out = _writable_dir(out)
    try:
        return _run(scene, scene_path, folder, args, device, config, resume)
    except BaseException:
        if created and not any(out.iterdir()):
            out.rmdir()  # leave nothing behind for a run that wrote nothing
        raise


def _run(scene, scene_path: Path, folder, args, device: str, config, resume: bool) -> dict:
    from ngp_warp.checkpoint import load_trainer, save_checkpoint
    from ngp_warp.camera_path import around_cameras
    from ngp_warp.video_out import render_trainer_video
    from ngp_warp.evaluate import evaluate
    from ngp_warp.refined_transforms import write_refined_transforms

    out = folder.path
    ckpt = out / CHECKPOINT
    downscale = args.downscale or 1
    if resume:
        trainer, record = load_trainer(ckpt, device=device, scene_path=scene_path)  # the same views
        if args.downscale not in (None, record["downscale"]):
            raise UserError(f"--downscale {args.downscale} with --resume: {out} trained at --downscale "
                            f"{record['downscale']} (a resumed run keeps it)")
        trainer.config.steps, trainer.config.seconds = args.steps, args.seconds
        downscale = record["downscale"]
        print(f"resuming from {ckpt} at step {trainer.step_count}", file=sys.stderr)
    else:
        trainer = new_trainer(scene, config, device)
    if getattr(args, "data_parallel", False):  # rank 0 alone reports, saves and evaluates
        from ngp_warp.distributed import is_main_rank, make_data_parallel

        make_data_parallel(trainer)
        if not is_main_rank():
            return trainer.train(show_progress=False)
    scene = trainer.scene
    print(f"scene {scene_path} ({scene.source}): {len(scene.train.names)} train views "
          f"{scene.train.width}x{scene.train.height}, device {trainer.device}, finest hash-grid "
          f"level {trainer.config.field.finest_resolution:g} cells, table 2^{trainer.config.field.log2_hashmap_size} "
          f"per level, distortion loss weight {trainer.config.distortion_weight:g}"
          f"{f' ({trainer.config.distortion_spacing})' if trainer.config.distortion_weight else ''}, "
          f"{trainer.config.supersample}x{trainer.config.supersample} rays per pixel", file=sys.stderr)
    if scene.test_is_heldout:
        print(f"no test split: evaluating on {len(scene.test.names)} frames held out of training",
              file=sys.stderr)

    def save() -> None:  # an overwritten run's outputs go just before the first (good) write
        save_checkpoint(trainer, ckpt, scene_path, downscale, before_write=folder.claim)

    _train(trainer, save, folder, args)
    save()
    if trainer.cameras is not None:
        refined = write_refined_transforms(trainer, scene_path, downscale, out)
        print(f"camera refinement: {trainer.cameras.summary()}; refined poses: {refined}", file=sys.stderr)
    metrics = evaluate(trainer, out, show_progress=not args.quiet)
    if not args.no_video:
        train = scene.train
        centre = ((scene.aabb[:3] + scene.aabb[3:]) / 2).cpu()
        orbit = around_cameras("orbit", train.c2w, train.intrinsics, train.width, train.height, centre,
                               args.frames, ORBIT_FPS)
        video = render_trainer_video(trainer, orbit, out / "orbit.mp4", depth=False, quiet=args.quiet)[0]
        print(f"orbit video: {video}", file=sys.stderr)
    return metrics


def _train(trainer, save, folder, args) -> None:
    """Train, saving every ``--checkpoint-every`` seconds and on Ctrl-C or SIGTERM (then
    re-raised); a diverged run stops with one line, its last good checkpoint kept."""
    from ngp_warp.run_folder import Terminated
    from ngp_warp.trainer import TrainingDiverged

    ckpt = folder.path / CHECKPOINT
    try:
        trainer.train(show_progress=not args.quiet, checkpoint=save, checkpoint_every=args.checkpoint_every)
    except KeyboardInterrupt as e:  # Ctrl-C, or SIGTERM (main's sigterm_as_interrupt)
        save()
        how = "terminated (SIGTERM)" if isinstance(e, Terminated) else "interrupted"
        resume = "--resume" if hasattr(args, "resume") else f"ngp-warp train {folder.path / 'scene'} --resume"
        print(f"ngp-warp: {how} at step {trainer.step_count}; checkpoint saved to {ckpt} "
              f"(continue with {resume})", file=sys.stderr)
        raise
    except TrainingDiverged as e:
        kept = ("nothing was saved" if not ckpt.exists() else f"{ckpt} keeps the last good checkpoint"
                if folder.claimed else f"{folder.path} still holds the previous run")
        raise UserError(f"{e}; {kept}") from None


def _print_metrics(metrics: dict, out: Path) -> None:
    ssim = "n/a (images under 11 px)" if metrics["ssim"] is None else f"{metrics['ssim']:.4f}"
    psnr = "n/a (not finite)" if metrics["psnr"] is None else f"{metrics['psnr']:.2f} dB"
    print(f"{metrics['test_split']}: PSNR {psnr}  SSIM {ssim}  "
          f"({metrics['n_test_images']} images, {metrics['steps']} steps, "
          f"{metrics['train_seconds']:.1f} s training on {metrics['device']})")
    if metrics.get("psnr_mean_code") is not None:
        fitted = "appearance code and pose" if " and pose " in metrics["appearance"] else "appearance code"
        print(f"  (right halves, each view's {fitted} fitted on its left half; whole images with the nearest "
              f"training view's code: PSNR {metrics['psnr_nearest_code']:.2f} dB, the mean code: "
              f"{metrics['psnr_mean_code']:.2f} dB)")
    print(f"wrote {out / 'metrics.json'}, {out / 'renders'}/, {out / 'depth'}/, {out / CHECKPOINT}")


def cmd_train(args) -> None:
    scene = Path(args.scene)
    if args.resume and args.set:
        raise UserError("--set with --resume: a resumed run keeps the settings in its checkpoint")
    if args.resume and args.overwrite:
        raise UserError("--resume with --overwrite: continue the run in --out, or replace it, not both")
    config = None if args.resume else _train_config(args)  # bad settings fail before any loading
    from ngp_warp.distributed import join_data_parallel

    args.data_parallel = join_data_parallel(args)  # under torchrun: this rank's device in args.device
    metrics = _train_and_report(scene, Path(args.out), args, config=config)
    if metrics is not None:  # None on ranks other than 0
        _print_metrics(metrics, Path(args.out))


def cmd_demo(args) -> None:
    from ngp_warp.demo import DEMOS
    from ngp_warp.run_folder import RunFolder

    # every option is checked before the scene is generated
    device = _device(args.device)
    demo = DEMOS[args.scene]
    config = _with_settings(demo.config(device, args.steps, args.seconds, args.seed), args)
    RunFolder(Path(args.out), overwrite=args.overwrite, flags=(None, "--overwrite"))
    out = _writable_dir(Path(args.out))
    scene_dir = out / demo.folder
    if not (scene_dir / "transforms_train.json").exists():
        print(f"generating the {args.scene} scene in {scene_dir}", file=sys.stderr)
        demo.write(scene_dir, seed=args.seed)
    metrics = _train_and_report(scene_dir, out, args, config=config)
    _print_metrics(metrics, out)


def cmd_eval(args) -> None:
    from ngp_warp.atomic import remove_stale_partials
    from ngp_warp.checkpoint import load_trainer
    from ngp_warp.evaluate import evaluate
    from ngp_warp.run_folder import check_output_names

    check_output_names(Path(args.dir))  # e.g. renders/ that is a file: refused before loading
    trainer, _ = load_trainer(Path(args.dir) / CHECKPOINT, device=_device(args.device), scene_path=args.scene)
    out = _writable_dir(Path(args.dir))
    remove_stale_partials(out)  # left by an evaluation that was killed
    _print_metrics(evaluate(trainer, out, show_progress=not args.quiet), out)


def cmd_render(args) -> None:
    from ngp_warp.checkpoint import load_trainer
    from ngp_warp.video_out import PATH_KINDS, camera_path_from_args, render_trainer_video

    video = Path(args.video)
    if video.suffix.lower() not in (".mp4", ".gif"):
        raise UserError(f"--video {video}: expected a .mp4 or .gif path")
    if args.path not in PATH_KINDS and not Path(args.path).is_file():
        raise UserError(f"--path {args.path}: no such file (or use {' or '.join(PATH_KINDS)})")
    trainer, record = load_trainer(Path(args.dir) / CHECKPOINT, device=_device(args.device), scene_path=args.scene)
    out = _writable_dir(Path(args.dir))
    if not video.is_absolute():
        video = out / video
    if not video.parent.is_dir():
        raise UserError(f"--video {video}: folder {video.parent} does not exist")
    try:
        path = camera_path_from_args(args, trainer.scene, record["path"])
    except ValueError as e:
        raise UserError(str(e)) from None
    for written in render_trainer_video(trainer, path, video, depth=args.depth_video, quiet=args.quiet):
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
        if not (value > 0 and math.isfinite(value)):
            raise argparse.ArgumentTypeError(f"expected a positive {kind.__name__}, got {text!r}")
        return value

    parse.__name__ = kind.__name__
    return parse


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value < 2**63:
        raise argparse.ArgumentTypeError(f"expected an integer in [0, 2^63), got {text!r}")
    return value


def _folder(text: str) -> str:
    if not text.strip():
        raise argparse.ArgumentTypeError("expected a folder, got an empty name")
    return text


def _parser() -> argparse.ArgumentParser:
    from ngp_warp.export import add_export_parser
    from ngp_warp.fit_many import add_fit_many_parser
    from ngp_warp.process import add_process_parser
    from ngp_warp.video_out import add_path_arguments
    from ngp_warp.viewer import add_view_parser

    p = argparse.ArgumentParser(prog="ngp-warp", description="instant-NGP radiance fields on Warp kernels (CPU or CUDA)")
    sub = p.add_subparsers(dest="command", required=True)

    def common(sp):
        sp.add_argument("--device", default="auto", help="cpu, cuda or cuda:N (default: cuda when present)")
        sp.add_argument("--quiet", action="store_true", help="no progress bars")

    def training(sp):
        budget = sp.add_mutually_exclusive_group()
        budget.add_argument("--steps", type=_positive(int), help="training steps")
        budget.add_argument("--seconds", type=_positive(float), help="training wall-clock budget in seconds")
        sp.add_argument("--downscale", type=_positive(int), help="shrink images by this integer factor (default 1)")
        sp.add_argument("--seed", type=_seed, default=0)
        sp.add_argument("--target-samples", type=_positive(int), help="samples per batch (default 2^18 CUDA, 2^15 CPU)")
        sp.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="any training setting, e.g. distortion_weight=0 or field.log2_hashmap_size=19 "
                             "(repeatable; see ngp_warp.config.TrainConfig)")
        sp.add_argument("--no-video", action="store_true", help="skip the orbit video")
        sp.add_argument("--frames", type=_positive(int), default=60, help="orbit video frames")
        sp.add_argument("--overwrite", action="store_true", help="replace the run already in the output folder")
        sp.add_argument("--checkpoint-every", type=_positive(float), default=300.0, metavar="SECONDS",
                        help="save a checkpoint this often while training (default 300; also on Ctrl-C and SIGTERM)")

    t = sub.add_parser("train", help="train on a scene folder, then evaluate and render")
    t.add_argument("scene", help="NeRF-synthetic folder or folder with an instant-ngp transforms.json")
    t.add_argument("--out", type=_folder, required=True, help="output folder")
    t.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    t.add_argument("--gpus", type=_positive(int), default=1, help="data-parallel ranks through torchrun (README)")
    training(t)
    common(t)
    t.set_defaults(func=cmd_train)

    d = sub.add_parser("demo", help="generate the built-in procedural scene, train and evaluate on it")
    d.add_argument("--out", type=_folder, default="ngp-warp-demo", help="output folder (default ./ngp-warp-demo)")
    d.add_argument("--scene", choices=("demo", "unbounded"), default="demo",  # ngp_warp.demo.DEMOS
                   help="demo: objects in a box, white background; unbounded: the 360° scene (objects "
                        "on a ground plane to the horizon, learned background, contracted space)")
    training(d)
    common(d)
    d.set_defaults(func=cmd_demo)

    e = sub.add_parser("eval", help="evaluate a trained output folder on its test split")
    e.add_argument("dir", type=_folder)
    e.add_argument("--scene", help="scene folder, if it moved since training")
    common(e)
    e.set_defaults(func=cmd_eval)

    r = sub.add_parser("render", help="render a video along a camera path from a trained output folder")
    r.add_argument("dir", type=_folder)
    r.add_argument("--video", default="orbit.mp4", help="video path (.mp4, or .gif; relative to DIR)")
    add_path_arguments(r, _positive(int), _positive(float))
    r.add_argument("--scene", help="scene folder, if it moved since training")
    common(r)
    r.set_defaults(func=cmd_render)

    common(add_export_parser(sub, _positive(int), _positive(float)))
    common(add_view_parser(sub, _positive(int)))
    add_process_parser(sub)

    add_fit_many_parser(sub, training, common, _folder, _positive(int))

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
    from ngp_warp.memory_estimate import SettingsTooLarge
    from ngp_warp.run_folder import SIGTERM_EXIT, RunFolderError, Terminated, sigterm_as_interrupt

    try:
        with sigterm_as_interrupt():
            args.func(args)
    except (UserError, DataError, CheckpointError, RunFolderError, SettingsTooLarge) as e:
        print(f"ngp-warp: error: {e}", file=sys.stderr)
        return 2
    except Terminated:
        print("ngp-warp: terminated (SIGTERM)", file=sys.stderr)
        return SIGTERM_EXIT
    except KeyboardInterrupt:
        print("ngp-warp: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
