"""``ngp-warp render``: a video along a camera path."""

from __future__ import annotations

import argparse
from pathlib import Path

from ngp_warp.cli.common import CHECKPOINT, UserError, output_file, positive, resolve_device
from ngp_warp.outputs.camera_path import FPS_RANGE, MAX_FRAMES


def add_path_arguments(parser: argparse.ArgumentParser) -> None:
    """``--path``, ``--frames``, ``--fps`` and ``--depth-video`` for ``ngp-warp render``."""
    parser.add_argument("--path", default="orbit", metavar="FILE|orbit|spiral",
                        help="camera path: a nerfstudio camera_path.json, an instant-ngp base_cam.json, "
                             "or orbit / spiral around the training cameras (default orbit)")
    parser.add_argument("--frames", type=positive(int, high=MAX_FRAMES), default=60,
                        help="frames of an orbit, a spiral or an instant-ngp path (nerfstudio paths bring their own)")
    parser.add_argument("--fps", type=positive(float, *FPS_RANGE), default=20.0,
                        help="frames per second (nerfstudio paths bring their own)")
    parser.add_argument("--dataparser-transforms", metavar="FILE",
                        help="nerfstudio's dataparser_transforms.json of the training a nerfstudio camera path "
                             "was made on: the path is mapped from nerfstudio's frame to the scene's")
    parser.add_argument("--depth-video", action="store_true", help="also write NAME_depth.mp4 (or .gif)")


def cmd_render(args) -> None:
    from ngp_warp.training.checkpoint import load_trainer
    from ngp_warp.training.model import FAR
    from ngp_warp.outputs.video_out import PATH_KINDS, camera_path_from_args, depth_path, render_trainer_video

    video = output_file(Path(args.dir), args.video, "--video", (".mp4", ".gif"))  # before any work
    if args.depth_video:
        output_file(video.parent, depth_path(video).name, "--depth-video", (video.suffix.lower(),))
    if args.path not in PATH_KINDS and not Path(args.path).is_file():
        raise UserError(f"--path {args.path}: no such file (or use {' or '.join(PATH_KINDS)})")
    if args.dataparser_transforms is not None and (args.path in PATH_KINDS or not Path(args.dataparser_transforms).is_file()):
        raise UserError(f"--dataparser-transforms {args.dataparser_transforms}: " + (
            "no such file" if args.path not in PATH_KINDS else f"maps a nerfstudio camera path, not --path {args.path}"))
    if args.near is not None and args.near >= FAR:
        raise UserError(f"--near must be below the rays' far distance {FAR:g}, got {args.near:g}")
    trainer, record = load_trainer(Path(args.dir) / CHECKPOINT, device=resolve_device(args.device), scene_path=args.scene)
    try:
        path = camera_path_from_args(args, trainer.scene, record["path"])
    except ValueError as e:
        raise UserError(str(e)) from None
    if args.near is not None:
        trainer.model.start_rays_at(args.near)
    for written in render_trainer_video(trainer, path, video, depth=args.depth_video, quiet=args.quiet):
        print(f"wrote {written}")
