"""instant-ngp's ``transforms.json`` keys that choose the frames or change the pixels, as its loader
(``nerf_loader.cu``) applies them, and the ones ngp-warp reads past without applying.

* ``n_frames``: only the first n frames, in ``file_path`` order (instant-ngp sorts the frames by
  their path string, then cuts).
* ``sharpness_discard_threshold`` with a per-frame ``sharpness`` (colmap2nerf writes it; the
  threshold is 0 unless given): a frame stays only if its sharpness exceeds the threshold times
  the mean over its neighbourhood in that order, frames ``i - 3`` up to ``i + 2`` (instant-ngp's
  window, cut at the ends; the last frame's leaves itself out).
* ``white_transparent`` / ``black_transparent``: pixels whose three colour channels are all 255
  (all 0) are transparent (alpha 0), as though the images had an alpha channel that says so.
* Read past with one warning, so that a capture that relies on them does not train silently
  without them: ``rolling_shutter`` (non-zero), a frame's ``transform_matrix_start`` and
  ``transform_matrix_end`` (the camera's motion during the exposure: the start pose is used, as
  instant-ngp's first pose), ``sharpen`` (non-zero), ``depth_path`` with an
  ``integer_depth_scale`` (depth supervision), ``envmap`` and ``<file_path>.alpha.<ext>`` images.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ngp_warp.data.data_error import DataError, number, short

NEIGHBOURS_BEFORE, NEIGHBOURS_AFTER = 3, 2  # instant-ngp's sharpness window: frames i - 3 .. i + 2
TRANSPARENT_KEYS = {"white_transparent": 255, "black_transparent": 0}  # key -> the colour made transparent
log = logging.getLogger("ngp_warp.data.loading")  # the loader's messages, as transforms_json's


def _path_key(frame: dict) -> str:
    path = frame.get("file_path")
    return path.replace("\\", "/") if isinstance(path, str) else ""


def chosen_frames(meta: dict, frames: list, source: Path) -> list:
    """``frames`` (the file's list) cut to ``n_frames`` and thinned by sharpness, as instant-ngp
    (module docstring); the list itself where the file has neither. DataError on a bad value."""
    cut = meta.get("n_frames")
    threshold = number(meta, "sharpness_discard_threshold", str(source)) \
        if "sharpness_discard_threshold" in meta else 0.0
    sharp = threshold > 0 and isinstance(frames[0], dict) and "sharpness" in frames[0]
    if cut is None and not sharp:
        return frames
    ordered = sorted(frames, key=lambda f: _path_key(f) if isinstance(f, dict) else "")
    if cut is not None:
        if isinstance(cut, bool) or not isinstance(cut, int) or cut < 1:
            raise DataError(f"{source}: n_frames must be a positive integer, got {short(cut)}")
        ordered = ordered[:cut]
    if not sharp:
        return ordered
    values = [number(f, "sharpness", f"{source} {_path_key(f)}") if isinstance(f, dict) and "sharpness" in f else 1.0
              for f in ordered]
    kept = []
    for i, frame in enumerate(ordered):
        window = values[max(0, i - NEIGHBOURS_BEFORE):min(i + NEIGHBOURS_AFTER + 1, len(ordered) - 1)]
        if not window or values[i] > threshold * sum(window) / len(window):
            kept.append(frame)
    dropped = len(ordered) - len(kept)
    if dropped:
        log.warning(f"ngp-warp: {source}: left out {dropped} of {len(ordered)} frames blurrier than "
                 f"{threshold:g} of their neighbours' mean sharpness (sharpness_discard_threshold)")
    if not kept:
        raise DataError(f"{source}: sharpness_discard_threshold {threshold:g} leaves no frame")
    return kept


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


def with_transparency(image: np.ndarray, colours: tuple[int, ...]) -> np.ndarray:
    """[H, W, 3 or 4] uint8 ``image`` with alpha 0 where every colour channel equals one of
    ``colours`` ([H, W, 4]; the image itself when ``colours`` is empty)."""
    if not colours:
        return image
    if image.shape[2] == 3:
        image = np.concatenate([image, np.full(image.shape[:2] + (1,), 255, np.uint8)], axis=2)
    else:
        image = image.copy()
    for value in colours:
        image[(image[..., :3] == value).all(axis=2), 3] = 0
    return image


def warn_ignored(meta: dict, frames: list, source: Path, base: Path) -> None:
    """One warning naming the instant-ngp keys of ``meta`` and its ``frames`` that change training
    but that ngp-warp does not apply (module docstring); nothing when there are none."""
    levels = [meta, *(f for f in frames if isinstance(f, dict))]
    found = []
    if any(_non_zero(d.get("rolling_shutter")) for d in levels):
        found.append("rolling_shutter")
    if any("transform_matrix_end" in d or "transform_matrix_start" in d for d in levels[1:]):
        found.append("transform_matrix_start/end (the start pose is used)")
    if any(_non_zero(d.get("sharpen")) for d in levels):
        found.append("sharpen")
    if _non_zero(meta.get("integer_depth_scale")) and any("depth_path" in d for d in levels[1:]):
        found.append("depth_path")
    if "envmap" in meta:
        found.append("envmap")
    if any(_alpha_image(base, f) for f in levels[1:]):
        found.append("<file_path>.alpha.<ext> images")
    if found:
        log.warning(f"ngp-warp: {source}: instant-ngp keys ngp-warp does not apply: {', '.join(found)}")


def _non_zero(value) -> bool:
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return value != 0
    if isinstance(value, (list, tuple)):
        return any(_non_zero(v) for v in value)
    return False


def _alpha_image(base: Path, frame: dict) -> bool:
    path = _path_key(frame)
    return bool(path) and (base / f"{path}.alpha{Path(path).suffix}").is_file()
