"""sample_pixels: the fused batch kernel against the torch camera model and alpha blending."""

import math

import pytest
import torch

from ngp_warp.ops.batch import sample_pixels
from ngp_warp.data.loading import Split, generate_rays
from ngp_warp.outputs.evaluate import composite_on


def random_split(n_images=5, width=23, height=17, channels=4, distortion=False, seed=0, fisheye=False) -> Split:
    g = torch.Generator().manual_seed(seed)
    images = torch.randint(0, 256, (n_images, height, width, channels), generator=g, dtype=torch.uint8)
    q, _ = torch.linalg.qr(torch.randn(n_images, 3, 3, generator=g))
    c2w = torch.cat([q, torch.randn(n_images, 3, 1, generator=g) * 3], dim=2)
    f = torch.rand(n_images, generator=g) * 20 + 15
    intrinsics = torch.stack([f, f * 1.1, width / 2 + torch.rand(n_images, generator=g),
                              height / 2 - torch.rand(n_images, generator=g)], dim=1)
    dist = (torch.rand(n_images, 6, generator=g) - 0.5) * 0.1 if distortion else torch.zeros(n_images, 6)
    dist[:, 4 if fisheye else 3:6 if fisheye else 4] = 0  # OpenCV: k4 = 0; fisheye: p1 = p2 = 0
    return Split(images, c2w, intrinsics, dist, [f"r_{i}" for i in range(n_images)], width, height, fisheye)


@pytest.mark.parametrize("channels", [3, 4])
@pytest.mark.parametrize("distortion,fisheye", [(False, False), (True, False), (False, True), (True, True)])
def test_matches_the_torch_camera_model_and_blending(channels, distortion, fisheye):
    split = random_split(channels=channels, distortion=distortion, fisheye=fisheye)
    b = sample_pixels(split, 4000, seed=7)
    k, px, py = b.pixels.long().unbind(-1)
    rays_o, rays_d = split.rays(k, px, py)
    torch.testing.assert_close(b.rays_o, rays_o, rtol=0, atol=1e-6)
    torch.testing.assert_close(b.rays_d, rays_d, rtol=0, atol=2e-5 if distortion else 1e-6)
    torch.testing.assert_close(b.target, composite_on(split.images[k, py, px], b.background), rtol=0, atol=1e-6)
    if channels == 4:
        assert b.background.std() > 0.2 and b.background.min() >= 0 and b.background.max() < 1
        alpha = split.images[k, py, px, 3]
        assert (alpha < 255).float().mean() > 0.9  # the blend is exercised
    else:
        assert torch.equal(b.background, torch.ones_like(b.background))


def test_draws_uniformly_and_depends_only_on_the_seed():
    split = random_split()
    b = sample_pixels(split, 20000, seed=1)
    k, px, py = b.pixels.long().unbind(-1)
    counts = torch.bincount(k, minlength=len(split)).float()
    assert (counts - 4000).abs().max() < 5 * math.sqrt(4000)
    assert px.min() == 0 and px.max() == split.width - 1 and py.min() == 0 and py.max() == split.height - 1
    again = sample_pixels(split, 20000, seed=1)
    assert torch.equal(again.pixels, b.pixels) and torch.equal(again.background, b.background)
    other = sample_pixels(split, 20000, seed=2)
    assert (other.pixels != b.pixels).any(-1).float().mean() > 0.99


def with_masks(split: Split, masks: torch.Tensor) -> Split:
    return Split(split.images, split.c2w, split.intrinsics, split.distortion, split.names, split.width,
                 split.height, split.fisheye, masks)


def test_a_mask_draws_again_where_it_leaves_pixels_out():
    split = random_split()
    g = torch.Generator().manual_seed(3)
    sparse = torch.rand(len(split), split.height, split.width, generator=g) < 0.2  # keeps a fifth
    b = sample_pixels(with_masks(split, sparse), 8000, seed=5)
    k, px, py = b.pixels.long().unbind(-1)
    assert sparse[k, py, px].float().mean() > 0.95  # 1 − 0.8^17 = 0.977 expected, 0.2 without redraws
    rays_o, rays_d = split.rays(k, px, py)  # rays, targets and backgrounds belong to the drawn pixel
    torch.testing.assert_close(b.rays_d, rays_d, rtol=0, atol=1e-6)
    torch.testing.assert_close(b.target, composite_on(split.images[k, py, px], b.background), rtol=0, atol=1e-6)
    # a mask that keeps everything draws what no mask draws
    full = sample_pixels(with_masks(split, torch.ones_like(sparse)), 8000, seed=5)
    plain = sample_pixels(split, 8000, seed=5)
    assert torch.equal(full.pixels, plain.pixels) and torch.equal(full.background, plain.background)
    # a mask that keeps nothing: every pixel stays where its last redraw fell, none kept
    empty = sample_pixels(with_masks(split, torch.zeros_like(sparse)), 100, seed=5)
    assert empty.pixels.shape == (100, 3)


@pytest.mark.parametrize("bad", [0, -3, 2.5])
def test_rejects_bad_counts(bad):
    with pytest.raises(ValueError, match="positive integer"):
        sample_pixels(random_split(), bad, seed=0)


@pytest.mark.cuda
@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize("sub", [1, 2, 3])
def test_cuda_draws_what_the_cpu_draws(sub, masked):
    split = random_split(distortion=True)
    if masked:
        split = with_masks(split, torch.rand(len(split), split.height, split.width,
                                             generator=torch.Generator().manual_seed(4)) < 0.3)
    cpu = sample_pixels(split, 5000, seed=3, sub=sub)
    gpu = sample_pixels(split.to("cuda"), 5000, seed=3, sub=sub)
    assert torch.equal(gpu.pixels.cpu(), cpu.pixels)
    for a, b in zip(gpu[:4], cpu[:4]):
        torch.testing.assert_close(a.cpu(), b, rtol=0, atol=1e-5)


@pytest.mark.parametrize("sub", [2, 3])
def test_sub_pixel_rays_share_their_pixel_and_sit_on_a_grid(sub):
    split = random_split(distortion=True)
    b = sample_pixels(split, 500, seed=3, sub=sub)
    k = sub * sub
    assert b.rays_d.shape == b.rays_o.shape == (500 * k, 3)
    assert b.target.shape == b.background.shape == b.pixels.shape == (500, 3)  # one row per pixel
    one = sample_pixels(split, 500, seed=3)  # the same pixels, colours and backgrounds as one ray each
    for ours, centred in zip((b.pixels, b.target, b.background), (one.pixels, one.target, one.background)):
        assert torch.equal(ours, centred)
    assert b.background.std() > 0.2
    img, px, py = b.pixels.long().repeat_interleave(k, 0).unbind(-1)
    grid = (torch.arange(sub) + 0.5) / sub - 0.5  # offsets from the pixel centre, x fastest
    dx, dy = grid.repeat(sub).repeat(500), grid.repeat_interleave(sub).repeat(500)
    rays_o, rays_d = generate_rays(split.c2w[img], split.intrinsics[img], split.distortion[img], px + dx, py + dy)
    torch.testing.assert_close(b.rays_d, rays_d, rtol=0, atol=2e-5)
    assert (b.rays_d[0::k] - b.rays_d[1::k]).norm(dim=-1).min() > 0  # not all through the centre
    with pytest.raises(ValueError, match="sub must be"):
        sample_pixels(split, 5, seed=0, sub=0)
