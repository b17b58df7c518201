"""``ngp-warp process --masks``: a mask per photo, for COLMAP's features and for training.

A mask is read as a training mask (``mask_path``) is: a pixel is kept where its first stored
channel is nonzero (a palette image's index, not its colour; alpha is ignored). ``process``
writes each one into the scene as ``masks/NAME.png`` (NAME the photo's file name, COLMAP's
naming), a grey PNG of 255 where kept and 0 where not, which COLMAP reads as it is (no features
on 0), and names it in the photo's frame of ``transforms.json`` (``"mask_path"``), so that
training leaves the same pixels out.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np

from ngp_warp.data.data_error import DataError
from ngp_warp.data.images import mask_keeps, mask_values

MASKS_DIR = "masks"


def mask_for(photo: str, folder: Path) -> Path | None:
    """The mask of photo file ``photo`` in ``folder``: ``photo.png`` (COLMAP's naming, e.g.
    ``0001.jpg.png``) or ``STEM.png`` (nerfstudio's, ``0001.png``); None when neither exists."""
    for name in (f"{photo}.png", f"{Path(photo).stem}.png"):
        if (folder / name).is_file():
            return folder / name
    return None


def check_masks(folder: Path, source: Path, scene: Path) -> None:
    """Refuse, before any work, masks that cannot go with ``source`` into ``scene``: ``folder``
    missing, ``source`` a video, the masks among the photos (they would be read as photos), or
    inside ``scene`` (which ``--overwrite`` replaces)."""
    if not folder.is_dir():
        raise DataError(f"--masks {folder}: no such folder")
    if source.is_file():
        raise DataError(f"--masks {folder}: masks go with a folder of photos, not a video ({source})")
    masks, scene = folder.resolve(), scene.resolve()
    if masks == source.resolve():
        raise DataError(f"--masks {folder}: keep the masks in a folder of their own, not among the photos")
    if masks == scene or scene in masks.parents:
        raise DataError(f"--masks {folder}: the masks cannot be inside the scene folder {scene} (it is replaced)")


def gather_masks(folder: Path, sizes: dict[str, tuple[int, int]], scene: Path) -> Path:
    """Write every photo's mask from ``folder`` into ``scene/masks/NAME.png`` (255 kept, 0 left
    out) and return that folder. ``sizes``: {photo name: (height, width)}.

    Raises:
        DataError: a photo has no mask (the count and the first named), two photos share one
            (``a.jpg`` and ``a.png`` both find ``a.png``), a mask is unreadable, or its size
            differs from its photo's.
    """
    from PIL import Image

    found = {name: mask_for(name, folder) for name in sizes}
    missing = [name for name, path in found.items() if path is None]
    if missing:
        raise DataError(f"--masks {folder}: no mask for {len(missing)} of {len(sizes)} photos (first: "
                        f"{missing[0]}; looked for {missing[0]}.png and {Path(missing[0]).stem}.png)")
    uses = Counter(found.values())
    shared = [name for name, path in found.items() if uses[path] > 1]
    if shared:
        raise DataError(f"--masks {folder}: photos {shared[0]} and {shared[1]} would share the mask "
                        f"{found[shared[0]].name}; name each mask after its whole photo name ({shared[0]}.png)")
    out = scene / MASKS_DIR
    out.mkdir()
    for name, path in found.items():
        values = mask_values(path)
        if values.shape[:2] != sizes[name]:
            raise DataError(f"{path}: mask is {values.shape[1]}x{values.shape[0]} but its photo {name} is "
                            f"{sizes[name][1]}x{sizes[name][0]}")
        keep = np.where(mask_keeps(values), 255, 0).astype(np.uint8)
        Image.fromarray(keep).save(out / f"{name}.png")
    return out


def name_masks(meta: dict) -> None:
    """Give every frame of ``meta`` (transforms.json, its images in ``images/``) its mask's
    ``mask_path``, relative to the scene."""
    for frame in meta["frames"]:
        frame["mask_path"] = f"{MASKS_DIR}/{Path(frame['file_path']).name}.png"
