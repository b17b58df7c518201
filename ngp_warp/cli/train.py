"""``ngp-warp train`` and ``ngp-warp demo``."""

from __future__ import annotations

import sys
from pathlib import Path

from ngp_warp.cli.common import (UserError, check_run_apart, no_probe, print_metrics, refuse_probe, resolve_device,
                                 train_and_report, train_config, with_settings, writable_dir)


def prefetch_scene_images(train_args: list[str]) -> None:
    """``ngp-warp train SCENE ...``: start decoding the scene's images before anything imports
    torch (:mod:`ngp_warp.data.prefetch`), for the usual form only (the scene first, no
    ``--resume``). ``--downscale N`` is read as given, since it picks a COLMAP scene's
    ``images_N/``; the loading reads anything the prefetch did not decode."""
    if not train_args or train_args[0].startswith("-") or "--resume" in train_args:
        return
    downscale = 1
    for flag, value in zip(train_args, train_args[1:] + [""]):
        name, equals, inline = flag.partition("=")
        if name != "--downscale" and len(name) > 3 and "--downscale".startswith(name):
            return  # an abbreviation the parser takes: left to the loading
        given = (inline if equals else value) if name == "--downscale" else None
        if given is not None:
            if not (given.isascii() and given.isdecimal()) or int(given) < 1:
                return  # the parser refuses it
            downscale = int(given)
    from ngp_warp.data.prefetch import start_prefetch

    start_prefetch(train_args[0], downscale)


def cmd_train(args) -> None:
    scene = Path(args.scene)
    if args.resume and args.set:
        raise UserError("--set with --resume: a resumed run keeps the settings in its checkpoint")
    if args.resume and args.overwrite:
        raise UserError("--resume with --overwrite: continue the run in --out, or replace it, not both")
    check_run_apart(Path(args.out), scene)
    config = None if args.resume else train_config(args)  # bad settings fail before any loading
    from ngp_warp.training.distributed import join_data_parallel

    args.data_parallel = join_data_parallel(args)  # one of several ranks: this rank's device in args.device
    if args.data_parallel:  # the ranks train one model: no probe (each rank's could decide apart)
        refuse_probe(config, "with data-parallel training (--gpus > 1)")
        config = no_probe(config)
    metrics = train_and_report(scene, Path(args.out), args, config=config)
    if metrics is not None:  # None on ranks other than 0
        print_metrics(metrics, Path(args.out))


def cmd_demo(args) -> None:
    from ngp_warp.training.demo import DEMOS
    from ngp_warp.training.run_folder import RunFolder

    # every option is checked before the scene is generated
    device = resolve_device(args.device)
    demo = DEMOS[args.scene]
    if (args.downscale or 1) > demo.pixels:
        raise UserError(f"--downscale {args.downscale}: the {args.scene} scene's images are {demo.pixels}x"
                        f"{demo.pixels} pixels")
    seed = args.seed or 0
    config = with_settings(demo.config(device, args.steps, args.seconds, seed), args)
    RunFolder(Path(args.out), overwrite=args.overwrite, flags=(None, "--overwrite"))
    out = writable_dir(Path(args.out))
    scene_dir = out / demo.folder
    if not (scene_dir / "transforms_train.json").exists():
        print(f"generating the {args.scene} scene in {scene_dir}", file=sys.stderr)
        demo.write(scene_dir, seed=seed)
    metrics = train_and_report(scene_dir, out, args, config=config)
    print_metrics(metrics, out)
