"""The photos ``ngp-warp process`` starts from: a folder's images, all of one size, or a
video's frames."""

from __future__ import annotations

import logging
import shutil
from collections import Counter
from pathlib import Path

from ngp_warp.data.data_error import DataError

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
log = logging.getLogger("ngp_warp.data.process_photos")


def image_sizes(folder: Path) -> dict[str, tuple[int, int]]:
    """{file name: (height, width)} of the images directly in ``folder``, in name order."""
    import imageio.v3 as iio

    sizes = {}
    for path in sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()):
        try:
            sizes[path.name] = tuple(iio.improps(path).shape[:2])
        except Exception as e:  # imageio's readers raise many types for a damaged file
            raise DataError(f"{path}: not a readable image ({type(e).__name__})") from None
    return sizes


def check_one_size(folder: Path, sizes: dict[str, tuple[int, int]]) -> None:
    """DataError naming a photo whose size differs from the commonest: the photos share one
    camera, and training takes one image size."""
    counts = Counter(sizes.values())
    if len(counts) > 1:
        (h, w), n = counts.most_common(1)[0]
        odd = next(name for name, size in sizes.items() if size != (h, w))
        raise DataError(f"{folder / odd}: photo is {sizes[odd][1]}x{sizes[odd][0]} but {n} of {len(sizes)} are "
                        f"{w}x{h}; photos of one size share one camera (crop, resize or leave out the others)")


def gather_photos(source: Path, images_dir: Path, frames: int | None, fps: float | None,
                  show_progress: bool) -> tuple[dict, bool]:
    """Fill ``images_dir`` from ``source``: a folder of photos of one size, copied, or a video,
    ``frames`` of it evenly spread (default 100) or ``fps`` a second.

    Returns:
        {name: (height, width)} of the images, and whether ``source`` is a video.
    """
    if not source.exists():
        raise DataError(f"{source}: no such file or folder (expected a folder of images or a video)")
    images_dir.mkdir()
    if source.is_dir():
        if frames is not None or fps is not None:
            raise DataError(f"{source}: a folder of photos; --frames and --fps choose frames of a video")
        sizes = image_sizes(source)
        if not sizes:
            raise DataError(f"{source}: no images ({', '.join(IMAGE_SUFFIXES)}) in this folder")
        check_one_size(source, sizes)
        for name in sizes:
            shutil.copy2(source / name, images_dir / name)
        return sizes, False
    from ngp_warp.data.video import extract_frames

    count = 100 if frames is None and fps is None else frames
    kept = extract_frames(source, images_dir, count=count, fps=fps, show_progress=show_progress)
    if frames is not None and len(kept) < frames:
        log.warning(f"ngp-warp: {source}: the video has {len(kept)} frames; all are kept (--frames {frames})")
    return image_sizes(images_dir), True
