"""The evaluation's image conversions: depth maps as uint8."""

import numpy as np
import torch

from ngp_warp.outputs.evaluate import depth_to_uint8


def test_depth_spans_the_opaque_pixels_near_bright():
    gen = torch.Generator().manual_seed(0)
    depth = 0.5 + 4 * torch.rand(24, 32, generator=gen)
    opacity = torch.rand(24, 32, generator=gen)
    img = depth_to_uint8(depth * opacity, opacity)  # the renderer's depth is weighted by opacity
    opaque = (opacity > 0.5).numpy()
    d = depth.numpy()
    want = 1.0 - (d - d[opaque].min()) / (d[opaque].max() - d[opaque].min())
    want = np.where(opaque, np.floor(want * 255 + 0.5), 0)
    assert img.dtype == np.uint8 and img.shape == (24, 32)
    assert np.abs(img.astype(int) - want).max() <= 1  # float32 rounding at .5
    assert img[opaque].max() == 255 and img[opaque].min() == 0 and (img[~opaque] == 0).all()


def test_depth_of_a_transparent_view_is_black():
    depth = torch.rand(8, 8) * 3
    assert (depth_to_uint8(depth, torch.full((8, 8), 0.2)) == 0).all()
