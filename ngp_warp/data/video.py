"""Frames from a video for structure from motion: evenly spread, the sharpest of each stretch.

The video is split into equal stretches (``count`` of them, or one per ``1 / fps`` seconds) and
each stretch keeps its sharpest frame, so motion-blurred frames are dropped. Sharpness is the
variance of the Laplacian of the frame's intensity (a blurred frame has weak second derivatives):

.. math::
    L = I_{y-1,x} + I_{y+1,x} + I_{y,x-1} + I_{y,x+1} - 4 I_{y,x},\\qquad
    \\mathrm{sharpness} = \\operatorname{Var}(L)

Decoding uses imageio-ffmpeg (the ``[process]`` extra), one pass over the video.
"""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np

from ngp_warp.data.data_error import DataError

JPEG_QUALITY = 95


def sharpness(image: np.ndarray) -> float:
    """Variance of the 4-neighbour Laplacian of ``image`` ([H, W, 3] uint8 RGB or [H, W] grey)."""
    grey = image.astype(np.float32)
    if grey.ndim == 3:
        grey = grey @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    lap = grey[:-2, 1:-1] + grey[2:, 1:-1] + grey[1:-1, :-2] + grey[1:-1, 2:] - 4.0 * grey[1:-1, 1:-1]
    return float(lap.var()) if lap.size else 0.0


def _open(video: Path):
    """imageio-ffmpeg's frame generator past its metadata, the metadata, and the frame count."""
    import imageio_ffmpeg

    try:
        n_frames, _ = imageio_ffmpeg.count_frames_and_secs(str(video))
        frames = imageio_ffmpeg.read_frames(str(video))
        meta = next(frames)
    except (OSError, RuntimeError, StopIteration) as e:
        raise DataError(f"{video}: not a video ffmpeg can read ({type(e).__name__})") from None
    if n_frames < 1 or not all(s > 0 for s in meta.get("size", (0, 0))):
        raise DataError(f"{video}: the video has no frames")
    return frames, meta, n_frames


def stretch_of_frames(n_frames: int, video_fps: float, count: int | None, fps: float | None) -> np.ndarray:
    """[n_frames] int64: the stretch each frame belongs to (frames of one stretch give one image).

    ``count``: that many equal stretches (at most one frame each); ``fps``: stretches of ``1 / fps``
    seconds of video (``video_fps`` frames a second)."""
    index = np.arange(n_frames)
    if count is not None:
        return index * min(count, n_frames) // n_frames
    if not video_fps > 0:
        raise DataError("the video does not say its frame rate: use --frames N instead of --fps")
    return np.floor(index / video_fps * fps + 1e-9).astype(np.int64)


def extract_frames(video: Path, out_dir: Path, count: int | None = None, fps: float | None = None,
                   show_progress: bool = True) -> list[Path]:
    """Write the sharpest frame of each stretch of ``video`` to ``out_dir/frame_NNNNN.jpg``.

    Args:
        video: a video file ffmpeg can read.
        out_dir: an existing folder.
        count: number of frames to keep (evenly spread), or
        fps: frames to keep per second of video. Exactly one of the two.
        show_progress: a progress bar over the decoded frames.

    Returns:
        The images written, in video order (their names sort in that order).

    Raises:
        DataError: the file is no readable video, or it has no frame rate and ``fps`` was asked.
    """
    from ngp_warp.progress import progress

    if (count is None) == (fps is None):
        raise ValueError("give exactly one of count and fps")
    frames, meta, n_frames = _open(Path(video))
    stretch = stretch_of_frames(n_frames, float(meta.get("fps") or 0.0), count, fps)
    width, height = meta["size"]
    best_score, best_image, current, written = -1.0, None, 0, []  # best_score < 0: no frame held
    with progress(total=n_frames, desc="frames", unit="frame", disable=not show_progress) as bar:
        for i, raw in enumerate(frames):
            k = int(stretch[min(i, n_frames - 1)])
            if k != current and best_score >= 0.0:  # a stretch ended: keep its sharpest
                written.append(_write(out_dir, len(written), best_image))
                best_score = -1.0
            current = k
            image = np.frombuffer(raw, dtype=np.uint8).reshape(height, width, 3)
            score = sharpness(image[::2, ::2] if max(width, height) > 1000 else image)
            if score > best_score:
                best_score, best_image = score, image
            bar.update()
    if best_score >= 0.0:
        written.append(_write(out_dir, len(written), best_image))
    return written


def _write(out_dir: Path, index: int, image: np.ndarray) -> Path:
    path = Path(out_dir) / f"frame_{index + 1:05d}.jpg"
    iio.imwrite(path, image, quality=JPEG_QUALITY)
    return path
