"""Videos along a camera path: mp4 through imageio-ffmpeg (the ``viewer`` extra) or a GIF when
it is not installed, an optional depth video beside it, and the ``ngp-warp render --path``
arguments."""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch
from ngp_warp.progress import progress

from ngp_warp.atomic import atomic_file
from ngp_warp.outputs.camera_path import CameraPath, around_cameras, load_camera_path, ngp_transform
from ngp_warp.training.memory_estimate import SettingsTooLarge, available_bytes

RenderFrame = Callable[[torch.Tensor, torch.Tensor, int, int], dict]
PATH_KINDS = ("orbit", "spiral")


def mp4_available() -> bool:
    """Whether imageio can write mp4 here (the optional imageio-ffmpeg package)."""
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        return False
    return True


def write_video(frames: np.ndarray, path: str | Path, fps: float) -> Path:
    """Write [N, H, W, 3] uint8 frames atomically: an .mp4 (H.264) when imageio-ffmpeg is
    installed, otherwise a looping .gif beside the requested path. Returns the path written."""
    path = Path(path)
    if path.suffix.lower() == ".mp4" and not mp4_available():
        path = path.with_suffix(".gif")
    with atomic_file(path) as tmp:
        if path.suffix.lower() == ".gif":
            iio.imwrite(tmp, frames, extension=".gif", duration=1000.0 / fps, loop=0)
        else:  # the temporary name has no .mp4 ending: name the format. H.264 (yuv420p) takes even
            # sizes: an odd side gets its last row or column repeated (not a resample)
            even = ((0, 0), (0, frames.shape[1] % 2), (0, frames.shape[2] % 2), (0, 0))
            iio.imwrite(tmp, np.pad(frames, even, mode="edge"), extension=".mp4", fps=fps, macro_block_size=2,
                        output_params=["-f", "mp4"])
        if tmp.stat().st_size == 0:  # ffmpeg reports some failures on stderr only
            raise OSError(f"{path}: the video writer wrote nothing")
    return path


def depth_video_frames(depths: list[torch.Tensor], opacities: list[torch.Tensor]) -> np.ndarray:
    """Depth frames [H, W] (Σ w t) and opacities [H, W] → [N, H, W, 3] uint8 grey, one scale for
    the whole video (near = bright; the 2nd to 98th percentile of the pixels more than half
    opaque spans the range; emptier pixels are black)."""
    d = torch.stack([dep.float().cpu() / op.float().cpu().clamp_min(1e-6) for dep, op in zip(depths, opacities)])
    mask = torch.stack([op.float().cpu() > 0.5 for op in opacities])
    if mask.any():
        values = d[mask]
        values = values[torch.randperm(values.numel())[: 1 << 20]]  # quantile's input limit
        lo, hi = torch.quantile(values, 0.02), torch.quantile(values, 0.98)
        d = (1.0 - (d - lo) / (hi - lo).clamp_min(1e-6)).clamp(0, 1)
    grey = (torch.where(mask, d, torch.zeros_like(d)) * 255.0 + 0.5).to(torch.uint8)
    return grey[..., None].expand(*grey.shape, 3).numpy()


def depth_path(video: Path) -> Path:
    """Where the depth video of ``video`` goes: ``NAME_depth.EXT`` beside it."""
    return video.with_name(f"{video.stem}_depth{video.suffix}")


def check_video_memory(n_frames: int, width: int, height: int, depth: bool) -> None:
    """SettingsTooLarge (one line) when the frames of a video, which the writer holds on the host
    (RGB bytes and their stack; with ``depth``, float32 depth and opacity too), need more memory
    than the host has free."""
    need = n_frames * width * height * (6 + (14 if depth else 0))
    free = available_bytes(torch.device("cpu"))
    if need > free:
        raise SettingsTooLarge(f"a video of {n_frames} frames at {width}x{height} needs about {need / 1e9:.1f} GB "
                               f"of host memory but {free / 1e9:.1f} GB are free: fewer frames or smaller ones")


def render_path_video(render_frame: RenderFrame, path: CameraPath, out: str | Path, depth: bool = False,
                      show_progress: bool = True) -> list[Path]:
    """Render every camera of ``path`` and write the video ``out`` (and its depth video with
    ``depth``, see :func:`depth_path`).

    Args:
        render_frame: (c2w [3, 4], intrinsics [4], width, height) → dict with ``rgb`` [H, W, 3]
            float in [0, 1] and, for the depth video, ``depth`` and ``opacity`` [H, W].

    Returns:
        The paths written (a .gif instead of an .mp4 without imageio-ffmpeg).
    """
    out = Path(out)
    check_video_memory(len(path.c2w), path.width, path.height, depth)
    frames, depths, opacities = [], [], []
    cameras = zip(path.c2w, path.intrinsics)
    for c2w, intrinsics in progress(cameras, desc="video", total=len(path.c2w), unit="frame", disable=not show_progress):
        rendered = render_frame(c2w, intrinsics, path.width, path.height)
        frames.append((rendered["rgb"].clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy())
        if depth:
            depths.append(rendered["depth"].float().cpu())
            opacities.append(rendered["opacity"].float().cpu())
    written = [write_video(np.stack(frames), out, path.fps)]
    if depth:
        written.append(write_video(depth_video_frames(depths, opacities), depth_path(out), path.fps))
    return written


# ---- command line -----------------------------------------------------------------------------

def render_trainer_video(trainer, path: CameraPath, out: Path, depth: bool, quiet: bool) -> list[Path]:
    """The video (and with ``depth`` its depth video) of a camera path through a trainer's field, on
    white (over the field's learned background where it has one, as in evaluation)."""
    background = trainer.view_background

    def frame(c2w, intrinsics, width, height):
        return trainer.render_image(c2w, intrinsics, width, height, background=background)

    with trainer.weights.averaged_in_field():  # swapped in once, not once a frame
        return render_path_video(frame, path, out, depth=depth, show_progress=not quiet)


def camera_path_from_args(args, scene, scene_dir: str | Path) -> CameraPath:
    """The camera path ``args.path`` names, for a scene (its training cameras, image size,
    ``aabb`` and source; ``scene_dir``: the folder whose transforms.json gives instant-ngp's
    unit-cube map), a nerfstudio path mapped back through ``args.dataparser_transforms`` where
    given. Raises ValueError with one line for a bad path file."""
    train = scene.train
    if args.path in PATH_KINDS:
        center = ((scene.aabb[:3] + scene.aabb[3:]) / 2).cpu()
        return around_cameras(args.path, train.c2w, train.intrinsics, train.width, train.height,
                              center, args.frames, args.fps)
    if not Path(args.path).is_file():
        raise ValueError(f"--path {args.path}: no such file (or use {' or '.join(PATH_KINDS)})")
    dataparser = args.dataparser_transforms
    if dataparser is not None and scene.source == "colmap":
        raise ValueError(f"--dataparser-transforms {dataparser}: this scene was read from a COLMAP model, whose "
                         "frame ngp-warp normalises its own way; a nerfstudio path maps onto a transforms.json scene")
    scale, offset = ngp_transform(scene_dir)
    path = load_camera_path(args.path, train.width, train.height, args.frames, args.fps, scale, offset, dataparser,
                            scene_dir)
    print(f"camera path {args.path}: {len(path.c2w)} frames {path.width}x{path.height} at {path.fps:g} fps",
          file=sys.stderr)
    return path
