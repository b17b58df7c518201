"""What the subcommands share: the run folder's checkpoint name, the one-line user error, the
device, output folders, the training settings and the train → checkpoint → evaluate → video path."""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from ngp_warp.training.run_folder import CHECKPOINT, TRAINING_CURVE

ORBIT_FPS = 20.0  # the training run's orbit video
MAX_DOWNSCALE = 1024  # --downscale: beyond it no image keeps a pixel
NAME_MAX = 255  # bytes in one file or folder name (Linux, macOS and Windows file systems)


class UserError(Exception):
    """A mistake in the command line or its inputs: reported as one line, no traceback."""


def resolve_device(name: str | None) -> str:
    from ngp_warp import _wp
    from ngp_warp.training.config import default_device

    if name in (None, "auto"):
        return default_device()
    if name.startswith("cuda") and not _wp.cuda_available():
        raise UserError(f"--device {name}: no CUDA GPU usable by torch and Warp on this machine (use --device cpu)")
    if name != "cpu" and not name.startswith("cuda"):
        raise UserError(f"--device {name}: expected cpu, cuda or cuda:N")
    return name


def writable_dir(path: Path) -> Path:
    """Create ``path`` if needed and prove we can write there, before any long work starts."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        _probe_write(path)
    except OSError as e:
        raise UserError(f"{path}: output folder is not writable ({e.strerror or e})") from None
    return path


def _probe_write(folder: Path) -> None:
    """Write and remove a file in ``folder`` (OSError when it takes none); the name is per
    process, as data-parallel ranks probe at once."""
    probe = folder / f".ngp-warp-write-test-{os.getpid()}"
    probe.write_text("")
    probe.unlink()


def check_run_apart(run: Path, scene: Path, flag: str = "--out") -> None:
    """UserError when the run folder ``run`` is the scene's folder (``scene``: a folder or a
    transforms file, when it exists), inside it, or holds it: the run would be written into the
    dataset."""
    if not scene.exists():
        return  # the loader names a scene that is not there
    dataset = (scene if scene.is_dir() else scene.parent).resolve()
    run = run.resolve()
    if run == dataset or dataset in run.parents or run in dataset.parents:
        raise UserError(f"{flag} {run}: the run folder would be, hold or sit inside the scene folder {dataset}, "
                        f"so the run would be written into the dataset (choose a folder apart from it)")


def output_file(out_dir: Path, name: str, flag: str, suffixes: tuple[str, ...]) -> Path:
    """The file ``name`` (relative to ``out_dir`` unless absolute) that ``flag`` asks a
    subcommand to write, vetted before any work: one of ``suffixes``, not a folder, in a folder
    that exists and takes a file (probed), a name the file system takes; UserError otherwise."""
    path = Path(name)
    path = path if path.is_absolute() else Path(out_dir) / path
    if path.suffix.lower() not in suffixes:
        raise UserError(f"{flag} {name}: expected a {' or '.join(suffixes)} path")
    if len(path.name.encode()) > NAME_MAX:
        raise UserError(f"{flag}: the file name is longer than the file system takes ({NAME_MAX} bytes)")
    if path.is_dir():
        raise UserError(f"{flag} {name}: is a folder, not a file")
    if not path.parent.is_dir():
        raise UserError(f"{flag} {name}: folder {path.parent} does not exist")
    try:
        _probe_write(path.parent)
    except OSError as e:
        raise UserError(f"{flag} {name}: cannot write in {path.parent} ({e.strerror or e})") from None
    return path


def with_settings(cfg, args):
    """``cfg`` with ``--target-samples`` and the ``--set KEY=VALUE`` settings applied."""
    from ngp_warp.training.config import apply_overrides

    if args.target_samples:
        cfg.target_samples = args.target_samples
    try:
        cfg = apply_overrides(cfg, args.set)
        cfg.check()
        return cfg
    except ValueError as e:
        raise UserError(f"--set: {e}") from None


def train_config(args, device: str | None = None):  # device: resolved already, else args.device's
    from ngp_warp.training.config import TrainConfig, cpu_sizes
    cfg = TrainConfig(steps=args.steps, seconds=args.seconds, seed=args.seed or 0)
    return with_settings(cpu_sizes(cfg) if (device or resolve_device(args.device)) == "cpu" else cfg, args)  # --set wins


def new_trainer(scene, config, device: str):
    """A Trainer; its ValueErrors, which name a setting that does not suit the scene, as UserError."""
    from ngp_warp.training.trainer import Trainer
    try:
        return Trainer(scene, config, device=device)
    except ValueError as e:
        raise UserError(f"--set: {e}") from None


def _check_video(args, scene) -> None:
    """The orbit video's frames fit in memory (checked before the work), unless ``--no-video``."""
    from ngp_warp.outputs.video_out import check_video_memory

    if not args.no_video:
        check_video_memory(args.frames, scene.train.width, scene.train.height, depth=False)


def refuse_probe(config, why: str) -> None:
    """UserError (before any loading) for ``contraction_fit`` "probe" where it cannot run."""
    from ngp_warp.training.scene_defaults import PROBE_FIT

    if config is not None and config.contraction_fit == PROBE_FIT:
        raise UserError(f"--set contraction_fit=probe: not supported {why}; give seen or cameras")


def no_probe(config):
    """``config`` with ``contraction_fit`` "auto" made "cameras" (a run that cannot probe); None
    (a resumed run) as it is."""
    from ngp_warp.training.scene_defaults import AUTO_FIT

    if config is None or config.contraction_fit != AUTO_FIT:
        return config
    return dataclasses.replace(config, contraction_fit="cameras")


def _new_probed_trainer(scene, config, device: str, show_progress: bool):
    """:func:`new_trainer`, its ``contraction_fit`` "auto" or "probe" decided by a short training
    where it probes (one line on stderr says what it saw), and what the probe saw (a
    ``ProbeResult``, None without one). Ctrl-C during the probe says that nothing was saved; a
    probe that diverges is a UserError."""
    from ngp_warp.training.contraction_probe import probed_trainer
    from ngp_warp.training.trainer import TrainingDiverged

    try:
        trainer, probe = probed_trainer(scene, config, device, make_trainer=new_trainer, show_progress=show_progress)
    except KeyboardInterrupt:
        print("ngp-warp: interrupted during the contraction probe, before the first checkpoint: nothing "
              "saved (run the command again)", file=sys.stderr)
        raise
    except TrainingDiverged as e:
        raise UserError(f"{e} (during the contraction probe; nothing was saved)") from None
    if probe is not None:
        fit = (config or trainer.config).contraction_fit
        print(_probe_line(probe, fit, trainer.config.aabb_scale), file=sys.stderr)
    return trainer, probe


def _probe_line(probe, fit: str, aabb_scale: int | None) -> str:
    """One line: what the contraction probe (a ``ProbeResult``) of ``contraction_fit`` ``fit`` saw
    and how the run trains (bounded in the box of ``aabb_scale``, None for the scene files')."""
    box = "the scene files' box" if aabb_scale is None else f"a box of {aabb_scale}"
    how = (f"bounded in {box}, as an object before a distant backdrop" if probe.fit == "bounded"
           else "contracted, the inner box holding the cameras")
    spent = f"{probe.steps} steps in {probe.seconds:.1f} s"
    saw = (f"{probe.share:.2f} of the density and {probe.cells:.2f} of the occupied cells inside the box the "
           f"cameras see after {spent}" if probe.share is not None
           else f"the budget is too short for a probe{f' (ended after {spent})' if probe.steps else ''}")
    return f"contraction_fit={fit}: {saw}: training {how}"


def train_and_report(scene_path: Path, out: Path, args, config=None) -> dict:
    """Train (or resume), checkpoint, evaluate and render into ``out`` (a folder of one run:
    :class:`ngp_warp.training.run_folder.RunFolder`)."""
    from ngp_warp.data.loading import load_scene
    from ngp_warp.data.prefetch import drop_prefetched
    from ngp_warp.training.run_folder import RunFolder
    from ngp_warp.training.train_step import capture_imports_alongside, uses_graphs

    device = resolve_device(args.device)
    out = Path(out)
    resume = getattr(args, "resume", False)
    folder = RunFolder(out, resume, args.overwrite, ("--resume" if hasattr(args, "resume") else None, "--overwrite"))
    graphs = config is not None and not resume and uses_graphs(config, device.split(":")[0])
    try:
        with capture_imports_alongside(graphs):  # the graphs' capture imports while the images decode
            scene = None if resume else load_scene(scene_path, downscale=args.downscale or 1)
    finally:
        drop_prefetched()  # what `train` started decoding early (ngp_warp.data.prefetch) and the loading left
    created = not out.exists()
    out = writable_dir(out)
    try:
        return _run(scene, scene_path, folder, args, device, config, resume)
    except BaseException:
        if created and not any(out.iterdir()):
            out.rmdir()  # leave nothing behind for a run that wrote nothing
        raise


def _run(scene, scene_path: Path, folder, args, device: str, config, resume: bool) -> dict:
    from ngp_warp.training.checkpoint import load_trainer
    from ngp_warp.outputs.camera_path import around_cameras
    from ngp_warp.outputs.video_out import render_trainer_video
    from ngp_warp.outputs.evaluate import write_metrics
    from ngp_warp.wall_clock import WallClock

    out = folder.path
    ckpt = out / CHECKPOINT
    downscale, probe = args.downscale or 1, None
    if resume:
        trainer, record = load_trainer(ckpt, device=device, scene_path=scene_path)  # the same views
        for flag, given, kept in (("--downscale", args.downscale, record["downscale"]),
                                  ("--seed", args.seed, trainer.config.seed),
                                  ("--target-samples", args.target_samples, trainer.target_samples)):
            if given not in (None, kept):
                raise UserError(f"{flag} {given} with --resume: {out} trained with {flag} {kept} "
                                "(a resumed run keeps it)")
        trainer.config.steps, trainer.config.seconds = args.steps, args.seconds
        downscale = record["downscale"]
        print(f"resuming from {ckpt} at step {trainer.step_count}", file=sys.stderr)
    else:
        _check_video(args, scene)  # before a probe trains
        trainer, probe = _new_probed_trainer(scene, config, device, show_progress=not args.quiet)
    if getattr(args, "data_parallel", False):  # rank 0 alone reports, saves and evaluates
        from ngp_warp.training.distributed import is_main_rank, make_data_parallel

        make_data_parallel(trainer)
        if not is_main_rank():
            return trainer.train(show_progress=False)
    scene = trainer.scene
    print(f"scene {scene_path} ({scene.source}): {len(scene.train.names)} train views "
          f"{scene.train.width}x{scene.train.height}, device {trainer.device}, finest hash-grid "
          f"level {trainer.config.field.finest_resolution:g} cells, table 2^{trainer.config.field.log2_hashmap_size} "
          f"per level, distortion loss weight {trainer.config.distortion_weight:g}"
          f"{f' ({trainer.config.distortion_spacing})' if trainer.config.distortion_weight else ''}, "
          f"{trainer.config.supersample}x{trainer.config.supersample} rays per pixel, starting "
          f"{trainer.config.near:g} from their camera", file=sys.stderr)
    if scene.test_is_heldout:
        print(f"no test split: evaluating on {len(scene.test.names)} frames held out of training",
              file=sys.stderr)

    save = run_saver(trainer, folder, scene_path, downscale)
    if resume:
        _check_video(args, scene)
    clock = WallClock(getattr(args, "started", time.perf_counter()))
    clock.mark("start_up")
    probe_seconds = 0.0 if probe is None else probe.seconds
    clock.shift(probe_seconds, "start_up", "training")  # the probe trained during the start-up
    _train(trainer, save, folder, args, scene_path)
    clock.mark("training")
    metrics = _save_and_evaluate(trainer, save, out, scene_path, downscale, clock, args.quiet)
    clock.mark("evaluation")
    if not args.no_video:
        train = scene.train
        centre = ((scene.aabb[:3] + scene.aabb[3:]) / 2).cpu()
        orbit = around_cameras("orbit", train.c2w, train.intrinsics, train.width, train.height, centre,
                               args.frames, ORBIT_FPS)
        video = render_trainer_video(trainer, orbit, out / "orbit.mp4", depth=False, quiet=args.quiet)[0]
        print(f"orbit video: {video}", file=sys.stderr)
        clock.mark("video")
    print(clock.summary(), file=sys.stderr)
    probed = {} if probe is None else {"contraction_probe": dataclasses.asdict(probe)}  # what it saw and chose
    return write_metrics(out, {**metrics, **probed, "wall_seconds": clock.seconds})  # TRAINING_KEYS


def run_saver(trainer, folder, scene_path: Path, downscale: int):
    """save(writer=None): the run's checkpoint, training curve and normalisation into ``folder``
    (a :class:`ngp_warp.training.run_folder.RunFolder`, claimed just before the first good write,
    so that an overwritten run's outputs go only then); with ``writer`` the checkpoint is written
    on that thread and its future returned."""
    from ngp_warp.data.loading import write_normalisation
    from ngp_warp.outputs.evaluate import write_training_curve
    from ngp_warp.training.checkpoint import save_checkpoint

    def save(writer=None):
        written = save_checkpoint(trainer, folder.path / CHECKPOINT, scene_path, downscale, before_write=folder.claim,
                                  writer=writer)
        write_training_curve(folder.path, trainer.curve)  # beside each checkpoint: it survives an interruption
        write_normalisation(folder.path, trainer.scene)  # the map back to the capture's frame, beside them
        return written
    return save


def _save_and_evaluate(trainer, save, out: Path, scene_path: Path, downscale: int, clock, quiet: bool) -> dict:
    """The final checkpoint (and refined transforms), written while the test views are scored;
    returns the metrics. Ctrl-C during the evaluation keeps the checkpoint and says how to score it."""
    from ngp_warp.outputs.evaluate import evaluate
    from ngp_warp.training.refined_transforms import write_refined_transforms

    with ThreadPoolExecutor(1, thread_name_prefix="checkpoint") as writer:  # written while evaluating
        written = save(writer)
        if trainer.cameras is not None:
            refined = write_refined_transforms(trainer, scene_path, downscale, out)
            print(f"camera refinement: {trainer.cameras.summary()}; refined poses: {refined}", file=sys.stderr)
        clock.mark("checkpoint")
        try:
            metrics = evaluate(trainer, out, show_progress=not quiet)
        except KeyboardInterrupt:
            failed = written.exception()  # once the write has ended
            kept = f"the trained checkpoint is kept (evaluate it with ngp-warp eval {out})" if failed is None \
                else f"the checkpoint was not written ({failed})"
            print(f"ngp-warp: evaluation stopped; {kept}", file=sys.stderr)
            raise
        written.result()
    return metrics


def _train(trainer, save, folder, args, scene_path: Path) -> None:
    """Train, saving every ``--checkpoint-every`` seconds and on Ctrl-C or SIGTERM (then
    re-raised); a diverged run stops with one line, its last good checkpoint kept."""
    from ngp_warp.training.run_folder import Terminated
    from ngp_warp.training.trainer import TrainingDiverged

    ckpt = folder.path / CHECKPOINT
    try:
        trainer.train(show_progress=not args.quiet, checkpoint=save, checkpoint_every=args.checkpoint_every)
    except KeyboardInterrupt as e:  # Ctrl-C, or SIGTERM (main's sigterm_as_interrupt)
        save()
        how = "terminated (SIGTERM)" if isinstance(e, Terminated) else "interrupted"
        resume = "--resume" if hasattr(args, "resume") else f"ngp-warp train {scene_path} --out {folder.path} --resume"
        print(f"ngp-warp: {how} at step {trainer.step_count}; checkpoint saved to {ckpt} "
              f"(continue with {resume})", file=sys.stderr)
        raise
    except TrainingDiverged as e:
        kept = ("nothing was saved" if not ckpt.exists() else f"{ckpt} keeps the last good checkpoint"
                if folder.claimed else f"{folder.path} still holds the previous run")
        raise UserError(f"{e}; {kept}") from None


TRAINING_KEYS = ("contraction_probe", "wall_seconds")  # metrics.json's keys from training, not evaluation


def print_metrics(metrics: dict, out: Path, trained: bool = True) -> None:
    """The scores on stdout, then the files written: the evaluation's, and with ``trained`` the
    training's (checkpoint, training curve, normalisation)."""
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
    from ngp_warp.data.loading import NORMALISATION_FILE

    training = f", {out / CHECKPOINT}, {out / TRAINING_CURVE}, {out / NORMALISATION_FILE}" if trained else ""
    print(f"wrote {out / 'metrics.json'}, {out / 'renders'}/, {out / 'depth'}/{training}")


def positive(kind, low=None, high=None):
    """An argparse type: a positive finite ``kind``, within [``low``, ``high``] where given."""
    bounds = "" if high is None else f" up to {high:g}" if low is None else f" in [{low:g}, {high:g}]"

    def parse(text: str):
        try:
            value = kind(text)
        except (ValueError, OverflowError):
            raise argparse.ArgumentTypeError(f"expected a positive {kind.__name__}{bounds}, got {text!r}") from None
        if not (value > 0 and math.isfinite(value)) or (low is not None and value < low) or \
                (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"expected a positive {kind.__name__}{bounds}, got {text!r}")
        return value

    parse.__name__ = kind.__name__
    return parse


def seed_number(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value < 2**63:
        raise argparse.ArgumentTypeError(f"expected an integer in [0, 2^63), got {text!r}")
    return value


def folder_name(text: str) -> str:
    """An argparse type: a folder's path, not empty, each of its names one the file system takes."""
    if not text.strip():
        raise argparse.ArgumentTypeError("expected a folder, got an empty name")
    if any(len(part.encode()) > NAME_MAX for part in Path(text).parts):
        raise argparse.ArgumentTypeError(f"a name in this path is longer than the file system takes ({NAME_MAX} bytes)")
    return text
