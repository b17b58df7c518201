"""``sample_pixels``: a training batch of random pixels in one Warp launch."""

from __future__ import annotations

from typing import NamedTuple

import torch

from ngp_warp import _wp
from ngp_warp.data.loading import Split
from ngp_warp.kernels import batch as K

MASK_REDRAWS = 16  # draws more of a pixel that its training mask leaves out (then it stays out)
_NO_MASK: dict[torch.device, torch.Tensor] = {}  # a one-byte stand-in per device, for launches without masks


class PixelBatch(NamedTuple):
    """Rays through random pixels of a split and their colours (float32 on the split's device),
    for n pixels of k = sub² rays each.

    rays_o, rays_d: [n k, 3] camera centres and unit directions (as
        :func:`ngp_warp.data.cameras.generate_rays`); rows j k ... (j + 1) k − 1 are pixel j's.
    target: [n, 3] pixel colours in [0, 1], alpha blended over ``background``.
    background: [n, 3] uniform random colours for images with alpha, else white.
    pixels: [n, 3] int32 (image index, px, py) of each pixel.
    """

    rays_o: torch.Tensor
    rays_d: torch.Tensor
    target: torch.Tensor
    background: torch.Tensor
    pixels: torch.Tensor


def sample_pixels(split: Split, n: int, seed: int, sub: int = 1) -> PixelBatch:
    """``n`` pixels drawn uniformly over all images of ``split`` (with replacement): rays,
    targets and backgrounds in one launch. The draw is a function of ``seed`` only (the same on
    CPU and CUDA): pass a new seed each step. With ``sub`` > 1 each pixel gets ``sub²`` rays on
    a regular sub-pixel grid (rows ``j sub² ... (j + 1) sub² − 1`` for pixel j, x fastest):
    ``n sub²`` rays for ``n`` targets (:func:`ngp_warp.ops.ray_loss.ray_loss` with
    ``rays_per_pixel=sub²`` takes their mean). With training masks (``split.masks``) a pixel
    they leave out is drawn again, up to :data:`MASK_REDRAWS` times; ``pixels`` says which pixel
    each row holds, so a caller can leave out the few still masked.

    .. math::
        \\mathrm{target} = \\mathrm{rgb}\\,a + \\mathrm{bg}\\,(1 - a), \\qquad \\mathrm{bg} \\sim U[0, 1)^3
    """
    if not (isinstance(n, int) and n > 0):
        raise ValueError(f"n must be a positive integer, got {n!r}")
    if not isinstance(seed, int):
        raise ValueError(f"seed must be an integer, got {seed!r}")
    if not (isinstance(sub, int) and sub >= 1):
        raise ValueError(f"sub must be a positive integer, got {sub!r}")
    images = split.images
    if not images.is_contiguous():
        raise ValueError("split.images must be contiguous")
    dev = images.device
    for name in ("c2w", "intrinsics", "distortion", "masks"):
        if getattr(split, name) is None:
            continue
        if getattr(split, name).device != dev:
            raise ValueError(f"split.{name} is on {getattr(split, name).device}, its images on {dev}")
    rays = n * sub * sub
    if split.masks is None:
        if dev not in _NO_MASK:
            _NO_MASK[dev] = torch.ones(1, dtype=torch.uint8, device=dev)
        masks, redraws = _NO_MASK[dev], 0
    else:
        masks, redraws = split.masks.contiguous().view(torch.uint8).reshape(-1), MASK_REDRAWS
    out = PixelBatch(*(torch.empty(m, 3, dtype=torch.float32, device=dev) for m in (rays, rays, n, n)),
                     torch.empty(n, 3, dtype=torch.int32, device=dev))
    _wp.launch(
        K.sample_pixels, rays,
        [seed & 0x7FFFFFFF, sub, len(split), split.width, split.height, images.shape[-1], split.lens_model,
         images.view(-1), masks, redraws, split.c2w.reshape(-1).contiguous(), split.intrinsics.contiguous(),
         split.distortion.contiguous(), out.pixels, out.rays_o, out.rays_d, out.target, out.background],
        _wp.device_of(images),
    )
    return out
