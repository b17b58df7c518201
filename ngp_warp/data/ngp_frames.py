"""instant-ngp's ``transforms.json`` keys that choose the frames or change the pixels, as its loader
(``nerf_loader.cu``) applies them, and the ones ngp-warp reads past without applying.

* ``n_frames``: only the first n frames, in natural order of ``file_path`` (numbers in names by
  value: instant-ngp sorts the frames so, then cuts).
* A per-frame ``sharpness`` (colmap2nerf writes it) on the first frame in that order: a frame
  stays only if its sharpness exceeds ``sharpness_discard_threshold`` (0 unless given, which
  drops only frames of sharpness 0 or less) times the mean over its neighbourhood in that
  order, frames ``i - 3`` up to ``i + 2`` (instant-ngp's window, cut at the ends; the last
  frame's leaves itself out; a lone frame stays).
* ``white_transparent`` / ``black_transparent``: pixels whose three colour channels are all 255
  (all 0) are transparent (alpha 0), as though the images had an alpha channel that says so
  (:func:`ngp_warp.data.images.with_transparency`).
* A frame's ``transform_matrix_start`` is its pose, as in instant-ngp.
* Read past with one warning, so that a capture that relies on them does not train silently
  without them: ``rolling_shutter`` (non-zero: the rolling shutter and the motion blur toward a
  frame's ``transform_matrix_end``), ``sharpen`` (non-zero), ``depth_path`` with an
  ``integer_depth_scale`` (depth supervision), ``envmap`` and ``<file_path>.alpha.<image's
  extension>`` images.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

from ngp_warp.data.data_error import DataError, number, short

NEIGHBOURS_BEFORE, NEIGHBOURS_AFTER = 3, 2  # instant-ngp's sharpness window: frames i - 3 .. i + 2
TRANSPARENT_KEYS = {"white_transparent": 255, "black_transparent": 0}  # key -> the colour made transparent
log = logging.getLogger("ngp_warp.data.loading")  # the loader's messages, as transforms_json's


def natural_key(s: str) -> list:
    """Sort key: numbers in ``s`` compare by value ("img2" before "img10"), letters without case."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", s)]


def _path_key(frame) -> list:
    path = frame.get("file_path") if isinstance(frame, dict) else None
    return natural_key(path.replace("\\", "/") if isinstance(path, str) else "")


def chosen_frames(meta: dict, frames: list, source: Path) -> list[int]:
    """The indices into ``frames`` (the file's list) of the frames instant-ngp keeps, cut to
    ``n_frames`` and thinned by sharpness (module docstring), in that order; every index, in the
    file's order, where neither applies. DataError on a bad value."""
    cut = meta.get("n_frames")
    threshold = number(meta, "sharpness_discard_threshold", str(source)) \
        if "sharpness_discard_threshold" in meta else 0.0
    ordered = sorted(range(len(frames)), key=lambda i: _path_key(frames[i]))
    if cut is not None:
        if isinstance(cut, bool) or not isinstance(cut, int) or cut < 1:
            raise DataError(f"{source}: n_frames must be a positive integer, got {short(cut)}")
        ordered = ordered[:cut]
    first = frames[ordered[0]]
    if not (isinstance(first, dict) and "sharpness" in first):
        return list(range(len(frames))) if cut is None else ordered
    values = [_sharpness(frames[i], source) for i in ordered]
    kept = []
    for k, i in enumerate(ordered):
        window = values[max(0, k - NEIGHBOURS_BEFORE):min(k + NEIGHBOURS_AFTER + 1, len(ordered) - 1)]
        if not window or values[k] > threshold * sum(window) / len(window):
            kept.append(i)
    dropped = len(ordered) - len(kept)
    if dropped:
        log.warning(f"ngp-warp: {source}: left out {dropped} of {len(ordered)} frames whose sharpness is "
                    f"at most {threshold:g} of their neighbours' mean (sharpness_discard_threshold)")
    if not kept:
        raise DataError(f"{source}: no frame is sharper than {threshold:g} of its neighbours' mean "
                        "(sharpness_discard_threshold)")
    return kept


def _sharpness(frame, source: Path) -> float:
    """A frame's ``sharpness`` (1 where it has none, as instant-ngp reads it)."""
    if isinstance(frame, dict) and "sharpness" in frame:
        return number(frame, "sharpness", f"{source} {frame.get('file_path')}")
    return 1.0


def transparent_colour(meta: dict, source: Path) -> tuple[int, ...]:
    """The colour values (255 and/or 0) whose pixels ``meta`` makes transparent."""
    colours = []
    for key, value in TRANSPARENT_KEYS.items():
        flag = meta.get(key, False)
        if not isinstance(flag, bool):
            raise DataError(f"{source}: {key} must be true or false, got {short(flag)}")
        if flag:
            colours.append(value)
    return tuple(colours)


def warn_ignored(meta: dict, frames: list[tuple[dict, Path]], source: Path) -> None:
    """One warning naming the instant-ngp keys of ``meta`` and its frames (each with its image's
    path) that change training but that ngp-warp does not apply (module docstring); nothing when
    there are none."""
    levels = [meta, *(f for f, _ in frames)]
    found = []
    if any(_non_zero(d.get("rolling_shutter")) for d in levels):
        found.append("rolling_shutter")
    if any(_non_zero(d.get("sharpen")) for d in levels):
        found.append("sharpen")
    if _non_zero(meta.get("integer_depth_scale")) and any("depth_path" in f for f, _ in frames):
        found.append("depth_path")
    if "envmap" in meta:
        found.append("envmap")
    if any(_alpha_image(f, image) for f, image in frames):
        found.append("<file_path>.alpha.<ext> images")
    if found:
        log.warning(f"ngp-warp: {source}: instant-ngp keys ngp-warp does not apply: {', '.join(found)}")


def _non_zero(value) -> bool:
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return value != 0
    if isinstance(value, (list, tuple)):
        return any(_non_zero(v) for v in value)
    return False


def _alpha_image(frame: dict, image: Path) -> bool:
    """Whether instant-ngp's alpha image of ``frame`` exists: ``<file_path>.alpha.<extension of the
    image read>``, beside the image (``file_path`` may leave the extension out)."""
    name = Path(frame["file_path"].replace("\\", "/")).name
    return (image.parent / f"{name}.alpha{image.suffix}").is_file()
