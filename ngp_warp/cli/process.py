"""``ngp-warp process``: photos or a video → a posed scene."""

from __future__ import annotations

from ngp_warp.cli.common import positive
from ngp_warp.data.data_error import DataError
from ngp_warp.outputs.camera_path import FPS_RANGE, MAX_FRAMES
from ngp_warp.data.process import CAMERA_MODELS, EXHAUSTIVE_MAX, EXTRA, MAPPERS, SIFT_KINDS, ProcessConfig, process, require_pycolmap

def add_process_parser(subparsers) -> None:
    """Register ``process`` on the CLI's subparsers."""
    p = subparsers.add_parser("process", help="photos or a video -> a posed scene (COLMAP via pycolmap; "
                                              f"needs {EXTRA})")
    p.add_argument("input", help="a folder of images (.jpg, .jpeg, .png) or a video file")
    p.add_argument("--out", required=True,
                   help="scene folder to create (images/, sparse/0, transforms.json; masks/ with --masks)")
    rate = p.add_mutually_exclusive_group()
    rate.add_argument("--frames", type=positive(int, high=MAX_FRAMES),
                      help="video: keep this many frames, evenly spread (default 100)")
    rate.add_argument("--fps", type=positive(float, high=FPS_RANGE[1]),
                      help="video: keep this many frames per second of video")
    p.add_argument("--matcher", default="auto", choices=("auto", "exhaustive", "sequential"),
                   help=f"auto: sequential for a video or over {EXHAUSTIVE_MAX} photos, else exhaustive")
    p.add_argument("--camera-model", default="SIMPLE_RADIAL", choices=CAMERA_MODELS,
                   help="COLMAP camera model (default: COLMAP's own, f cx cy k1)")
    p.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"),
                   help="SIFT on the GPU when pycolmap has CUDA (auto), or force cpu or cuda")
    p.add_argument("--sift", default=ProcessConfig.sift, choices=SIFT_KINDS,
                   help="dense: 16384 features, affine shapes, domain-size pooling (CPU); standard: COLMAP's")
    p.add_argument("--mapper", default=ProcessConfig.mapper, choices=MAPPERS, help="structure from motion's mapper")
    p.add_argument("--masks", metavar="DIR",
                   help="photos only: a mask per photo (NAME.png or STEM.png; 0 in its first channel = "
                        "leave out), used for the features and named in transforms.json for training")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out folder")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_process)


def cmd_process(args) -> None:
    """The ``process`` subcommand: run :func:`process` and print what it made."""
    config = ProcessConfig(frames=args.frames, fps=args.fps, matcher=args.matcher, camera_model=args.camera_model,
                           device=args.device, sift=args.sift, mapper=args.mapper, masks=args.masks,
                           overwrite=args.overwrite, show_progress=not args.quiet)
    try:
        config.check()
    except ValueError as e:
        raise DataError(str(e)) from None
    pycolmap = require_pycolmap()
    pycolmap.logging.minloglevel = 2  # COLMAP's own log: errors only (the bars show the progress)
    report = process(args.input, args.out, config)
    print(f"registered {report.registered} of {report.total} images, mean reprojection error "
          f"{report.mean_reprojection_error:.3f} px ({config.sift} SIFT on {report.sift_device}, {report.matcher} "
          f"matching, {report.mapper} mapping, "
          f"{report.seconds['total']:.1f} s)")
    masks = f", {report.scene / 'masks'}/" if config.masks is not None else ""
    scene = report.scene
    print(f"wrote {scene / 'transforms.json'}, {scene / 'sparse' / '0'}/, {scene / 'images'}/{masks}")
    if report.mapper != config.mapper:
        print(f"the {config.mapper} mapper's model contradicted its own matches; the {report.mapper} mapper's is kept")
    if report.contradicted:
        shown = ", ".join(report.contradicted[:6]) + (", ..." if len(report.contradicted) > 6 else "")
        print(f"warning: the poses of {len(report.contradicted)} image(s) contradict their own matches ({shown}): "
              f"each shares the most matches with a view posed on the other side of the subject, so the model "
              f"is probably folded by a symmetry of the subject; check the cameras with 'ngp-warp view {report.scene}' "
              f"and add views of what tells the sides apart")
