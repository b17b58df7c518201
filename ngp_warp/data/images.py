"""Image files of a scene: read in any 8/16-bit grey, grey+alpha, RGB or RGBA layout, checked,
downscaled by area averaging, and stacked (:func:`load_images`, on threads: Pillow decodes
without holding the GIL). Every problem raises :class:`DataError`, one line naming the file."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import imageio.v3 as iio
import numpy as np
from PIL import Image

from ngp_warp.data.data_error import DataError
from ngp_warp.data.transforms_json import Frame, log

PLAIN_MODES = ("RGB", "RGBA", "L", "LA")  # Pillow's 8-bit modes, whose pixels need no conversion


def _decoded(path: Path) -> np.ndarray:
    """The image's pixels as imageio's Pillow plugin reads them: an 8-bit image straight from
    Pillow (imageio's own steps cost about 1 ms an image, most of it holding the GIL that the
    loader's threads share), CMYK and other colour spaces converted to RGB by Pillow, any other
    mode (palettes, 16 bit) or a file Pillow cannot open through imageio, which converts it or
    says what is wrong."""
    try:
        with Image.open(path) as image:
            if image.mode in PLAIN_MODES:
                return np.asarray(image)
            if image.mode in ("CMYK", "YCbCr", "LAB", "HSV"):  # 4 or 3 channels that are not RGB(A)
                return np.asarray(image.convert("RGB"))
    except Exception:  # imageio reads it again below and raises what is wrong
        pass
    return np.asarray(iio.imread(path, plugin="pillow"))


def read_image(path: Path) -> np.ndarray:
    """[H, W, 3 or 4] uint8 from any 8/16-bit grey, grey+alpha, RGB or RGBA file."""
    try:
        a = _decoded(path)
    except Exception as e:  # imageio/Pillow raise many types for corrupt or unknown files
        reason = "not an image file Pillow can read" if "can not handle" in str(e) else str(e)
        raise DataError(f"{path}: cannot read image ({reason})") from None
    if a.dtype == np.uint16:
        a = ((a.astype(np.uint32) * 255 + 32767) // 65535).astype(np.uint8)
    elif a.dtype == np.bool_:
        a = a.astype(np.uint8) * 255
    elif a.dtype != np.uint8:
        raise DataError(f"{path}: unsupported pixel type {a.dtype} (8 or 16 bit images only)")
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[2] not in (1, 2, 3, 4) or 0 in a.shape:
        raise DataError(f"{path}: unsupported image layout {list(a.shape)}")
    if a.shape[2] <= 2:  # grey (+ alpha)
        a = np.concatenate([np.repeat(a[..., :1], 3, axis=2), a[..., 1:]], axis=2)
    return a


def downscale_image(a: np.ndarray, n: int) -> np.ndarray:
    """Area-average n x n blocks of a uint8 [H, W, C] image (cropped to multiples of n).

    RGBA is averaged premultiplied, so compositing the result on any background equals
    downscaling the composite: rgb = sum(rgb a) / sum(a), alpha = mean(a) (a block with no
    coverage keeps its plain mean colour).
    """
    if n == 1:
        return a
    h, w, c = a.shape[0] // n, a.shape[1] // n, a.shape[2]
    b = a[: h * n, : w * n].reshape(h, n, w, n, c).astype(np.float64)
    if c == 4:
        alpha = b[..., 3:]
        a_sum = alpha.sum(axis=(1, 3))
        rgb_premult = (b[..., :3] * alpha).sum(axis=(1, 3))
        rgb = np.where(a_sum > 0, rgb_premult / np.maximum(a_sum, 1e-12), b[..., :3].mean(axis=(1, 3)))
        out = np.concatenate([rgb, a_sum / (n * n)], axis=-1)
    else:
        out = b.mean(axis=(1, 3))
    return np.clip(np.floor(out + 0.5), 0, 255).astype(np.uint8)


def with_opaque_alpha(a: np.ndarray) -> np.ndarray:
    """uint8 images [..., 3] with an alpha channel of 255 added: [..., 4]."""
    return np.concatenate([a, np.full(a.shape[:-1] + (1,), 255, np.uint8)], axis=-1)


def with_transparency(image: np.ndarray, colours: tuple[int, ...]) -> np.ndarray:
    """[H, W, 3 or 4] uint8 ``image`` with alpha 0 where every colour channel equals one of
    ``colours`` ([H, W, 4]; the image itself when ``colours`` is empty): instant-ngp's
    ``white_transparent`` / ``black_transparent`` (:mod:`ngp_warp.data.ngp_frames`)."""
    if not colours:
        return image
    image = with_opaque_alpha(image) if image.shape[2] == 3 else image.copy()
    for value in colours:
        image[(image[..., :3] == value).all(axis=2), 3] = 0
    return image


def load_images(frames: list[Frame], downscale: int, read=None) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """Read (with ``read``, a path's [H, W, 3 or 4] uint8 as :func:`read_image`'s, which is the
    default), check and downscale every frame's image -> ([N, h, w, C] uint8, original (W, H)s)."""
    read = read or read_image

    def load(frame: Frame):
        a = with_transparency(read(frame.image), frame.transparent)
        if a.shape[0] < downscale or a.shape[1] < downscale:
            raise DataError(f"{frame.image}: image is {a.shape[1]}x{a.shape[0]}, smaller than downscale {downscale}")
        return (a.shape[1], a.shape[0]), downscale_image(a, downscale)

    out, sizes = None, []
    pool = ThreadPoolExecutor(max_workers=min(16, os.cpu_count() or 1))
    try:
        for k, (size, img) in enumerate(pool.map(load, frames)):
            if sizes and size != sizes[0]:
                raise DataError(f"{frames[k].image}: image is {size[0]}x{size[1]} but the first image "
                                f"({frames[0].image.name}) is {sizes[0][0]}x{sizes[0][1]}")
            sizes.append(size)
            if out is None:
                out = np.empty((len(frames), *img.shape), dtype=np.uint8)
            if img.shape[2] > out.shape[3]:  # the first RGBA image after RGB ones: add opaque alpha
                out = with_opaque_alpha(out)
            elif img.shape[2] < out.shape[3]:
                img = with_opaque_alpha(img)
            out[k] = img
    finally:
        pool.shutdown(wait=True, cancel_futures=True)  # after an error, skip the images not yet read
    return out, sizes


def load_masks(frames: list[Frame], sizes: list[tuple[int, int]], downscale: int) -> np.ndarray | None:
    """The frames' training masks (nerfstudio's ``mask_path``: train on the pixels whose first
    channel is nonzero; instant-ngp's dynamic masks, ``Frame.mask_marks_out``: on the black
    ones) -> [N, h, w] bool, a pixel of a downscaled image kept only where its whole block is;
    a frame without a mask keeps every pixel. None when no frame has one. ``sizes`` are the
    images' original (W, H), which each mask must match."""
    if all(f.mask is None for f in frames):
        return None
    w, h = sizes[0][0] // downscale, sizes[0][1] // downscale
    out = np.ones((len(frames), h, w), dtype=bool)
    for k, frame in enumerate(frames):
        if frame.mask is None:
            continue
        a = mask_values(frame.mask)
        if (a.shape[1], a.shape[0]) != sizes[k]:
            raise DataError(f"{frame.mask}: mask is {a.shape[1]}x{a.shape[0]} but its image "
                            f"({frame.image.name}) is {sizes[k][0]}x{sizes[k][1]}")
        keep = mask_keeps(a[: h * downscale, : w * downscale], frame.mask_marks_out)
        out[k] = keep.reshape(h, downscale, w, downscale).all(axis=(1, 3))
    empty = [f.mask.name for f, m in zip(frames, out) if not m.any()]
    if empty:
        log.warning(f"ngp-warp: {len(empty)} training mask(s) leave out every pixel (first: {empty[0]})")
    return out


def mask_keeps(values: np.ndarray, marks_out: bool = False) -> np.ndarray:
    """[H, W] bool the pixels a mask's stored ``values`` ([H, W, C], :func:`mask_values`) keep:
    nerfstudio's ``mask_path`` keeps those whose first channel is nonzero; instant-ngp's dynamic
    masks (``marks_out``) keep the black ones (every colour channel 0; alpha ignored)."""
    if not marks_out:
        return values[..., 0] > 0
    colour = values[..., :1] if values.shape[2] <= 2 else values[..., :3]  # grey (+ alpha) or RGB(A)
    return (colour == 0).all(axis=2)


def mask_values(path: Path) -> np.ndarray:
    """[H, W, C] a mask file's stored values: a palette image's indices, a grey image's levels."""
    try:
        with Image.open(path) as im:
            a = np.asarray(im)
    except Exception as e:  # Pillow raises many types for corrupt or unknown files
        raise DataError(f"{path}: cannot read mask ({e})") from None
    return a[..., None] if a.ndim == 2 else a
