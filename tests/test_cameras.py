"""Camera models: the torch ray generator against the float64 forward models of
``ngp_warp._reference.cameras``, and the Warp ray kernel against the torch generator, for the
pinhole, OpenCV (k1 k2 k3 p1 p2) and OpenCV fisheye (k1..k4) lenses."""

import math

import numpy as np
import pytest
import torch
from data_fixtures import random_c2w

from ngp_warp import _wp
from ngp_warp._reference.cameras import distort, fisheye_distort, project
from ngp_warp.data.cameras import LENS_FISHEYE, LENS_OPENCV, LENS_PINHOLE, fisheye_ray, generate_rays, undistort, view_rays
from ngp_warp.data.loading import Split
from ngp_warp.kernels import batch as K

OPENCV = [-0.15, 0.03, -0.004, 0.0, 0.004, -0.003]
FISHEYE = [0.08, -0.02, 0.004, -0.001, 0.0, 0.0]


def _random_rotation(n, generator=None):
    q, _ = torch.linalg.qr(torch.randn(n, 3, 3, dtype=torch.float64, generator=generator))
    return q


def _cameras(n, dtype=torch.float32):
    c2w = torch.cat([_random_rotation(n), torch.randn(n, 3, 1, dtype=torch.float64)], dim=2).to(dtype)
    intr = torch.tensor([[50.0, 45.0, 16.0, 12.0]], dtype=dtype).repeat(n, 1)
    return c2w, intr


def test_generate_rays_centre_pixel_looks_down_minus_z_opengl_axes():
    c2w, intr = _cameras(5)
    px = torch.full((5,), 15)
    intr[:, 2] = 15.5  # the centre of pixel 15 is 15.5: the ray through it hits cx exactly
    intr[:, 3] = 11.5
    o, d = generate_rays(c2w, intr, None, px, torch.full((5,), 11))
    torch.testing.assert_close(o, c2w[:, :, 3])
    torch.testing.assert_close(d, -c2w[:, :, 2])
    # one pixel right: towards camera +x; one pixel down: towards camera -y
    _, right = generate_rays(c2w, intr, None, px + 1, torch.full((5,), 11))
    _, down = generate_rays(c2w, intr, None, px, torch.full((5,), 12))
    cam_right = torch.einsum("bji,bj->bi", c2w[:, :, :3], right)
    cam_down = torch.einsum("bji,bj->bi", c2w[:, :, :3], down)
    assert (cam_right[:, 0] > 0).all() and cam_right[:, 1].abs().max() < 1e-6
    assert (cam_down[:, 1] < 0).all() and cam_down[:, 0].abs().max() < 1e-6
    torch.testing.assert_close(cam_right[:, 0] / -cam_right[:, 2], torch.full((5,), 1 / 50.0))
    # the fisheye's centre ray is the optical axis too
    _, fish = generate_rays(c2w, intr, torch.tensor([FISHEYE]).repeat(5, 1), px, torch.full((5,), 11), fisheye=True)
    torch.testing.assert_close(fish, -c2w[:, :, 2])


def test_generate_rays_zero_distortion_is_identity_and_dtype_follows_c2w():
    for dtype in (torch.float32, torch.float64):
        c2w, intr = _cameras(64, dtype)
        px, py = torch.randint(0, 32, (64,)), torch.randint(0, 24, (64,))
        o1, d1 = generate_rays(c2w, intr, None, px, py)
        o2, d2 = generate_rays(c2w, intr, torch.zeros(64, 6, dtype=dtype), px, py)
        assert d1.dtype == dtype and torch.equal(o1, o2) and torch.equal(d1, d2)
        torch.testing.assert_close(d1.norm(dim=-1), torch.ones(64, dtype=dtype))


def _coefficients(n, g, fisheye):
    """[n, 6] random float64 coefficients of one lens model (never all zero)."""
    u = torch.rand(n, 6, dtype=torch.float64, generator=g) - 0.5
    if fisheye:
        return u * torch.tensor([0.1, 0.02, 0.004, 0.001, 0.0, 0.0], dtype=torch.float64)  # monotonic to 85°
    return u * torch.tensor([0.4, 0.1, 0.04, 0.0, 0.02, 0.02], dtype=torch.float64)


def test_undistort_inverts_distort_with_k3():
    g = torch.Generator().manual_seed(3)
    n = 500
    x, y = (torch.rand(2, n, dtype=torch.float64, generator=g) - 0.5) * 1.2
    dist = _coefficients(n, g, fisheye=False)
    xd, yd = distort(x, y, dist)
    assert (xd - x).abs().max() > 1e-2  # the distortion is not negligible
    no_k3 = dist.clone()
    no_k3[:, 2] = 0
    assert (distort(x, y, no_k3)[0] - xd).abs().max() > 1e-4  # nor is k3's share
    ux, uy = undistort(xd, yd, dist)
    torch.testing.assert_close(ux, x, atol=1e-10, rtol=0)
    torch.testing.assert_close(uy, y, atol=1e-10, rtol=0)


def test_fisheye_ray_inverts_the_equidistant_model():
    g = torch.Generator().manual_seed(4)
    n = 500
    theta = torch.rand(n, dtype=torch.float64, generator=g) * math.radians(85)  # up to 85 degrees off axis
    phi = torch.rand(n, dtype=torch.float64, generator=g) * 2 * math.pi
    ray = torch.stack([theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos()], dim=-1)
    dist = _coefficients(n, g, fisheye=True)
    xd, yd = fisheye_distort(ray, dist)
    assert (xd.hypot(yd) - theta).abs().max() > 1e-2  # the polynomial matters
    torch.testing.assert_close(fisheye_ray(xd, yd, dist), ray, atol=1e-10, rtol=0)
    # by hand: no coefficients, 60 degrees off axis along +x lands at x_d = pi / 3
    got = fisheye_ray(torch.tensor([math.pi / 3], dtype=torch.float64), torch.zeros(1, dtype=torch.float64),
                      torch.zeros(1, 6, dtype=torch.float64))
    torch.testing.assert_close(got, torch.tensor([[math.sin(math.pi / 3), 0.0, 0.5]], dtype=torch.float64))


@pytest.mark.parametrize("lens", ["pinhole", "opencv", "fisheye"])
def test_rays_project_back_to_their_pixels(lens):
    n = 300
    c2w, intr = _cameras(n, torch.float64)
    g = torch.Generator().manual_seed(5)
    dist = None if lens == "pinhole" else _coefficients(n, g, lens == "fisheye")
    px, py = torch.randint(0, 32, (n,), generator=g), torch.randint(0, 24, (n,), generator=g)
    o, d = generate_rays(c2w, intr, dist, px, py, fisheye=lens == "fisheye")
    u, v = project(o + 2.5 * d, c2w, intr, dist, fisheye=lens == "fisheye")
    torch.testing.assert_close(u, px.double() + 0.5, atol=1e-8, rtol=0)
    torch.testing.assert_close(v, py.double() + 0.5, atol=1e-8, rtol=0)


def test_generate_rays_rejects_bad_shapes():
    c2w, intr = _cameras(4)
    px = torch.zeros(4, dtype=torch.long)
    for args in ((c2w[:, :2], intr, None, px, px), (c2w, intr[:3], None, px, px), (c2w, intr, None, px[:3], px),
                 (c2w, intr, torch.zeros(4, 4), px, px), (c2w.long(), intr, None, px, px), (c2w, intr, None, px, "y")):
        with pytest.raises(ValueError):
            generate_rays(*args)
    with pytest.raises(ValueError, match="fisheye rays need the distortion"):
        generate_rays(c2w, intr, None, px, px, fisheye=True)


# ---- the Warp kernel against the torch twin -------------------------------------------------------

def _split(lens: str, n_images=4, width=40, height=30) -> Split:
    rng = np.random.default_rng(6)
    g = torch.Generator().manual_seed(6)
    images = torch.randint(0, 256, (n_images, height, width, 3), generator=g, dtype=torch.uint8)
    c2w = torch.from_numpy(np.stack([random_c2w(rng)[:3] for _ in range(n_images)])).float()
    f = torch.rand(n_images, generator=g) * 10 + 25
    intrinsics = torch.stack([f, f * 1.1, width / 2 + torch.rand(n_images, generator=g),
                              height / 2 - torch.rand(n_images, generator=g)], dim=1)
    dist = torch.zeros(n_images, 6) if lens == "pinhole" else _coefficients(n_images, g, lens == "fisheye").float()
    return Split(images, c2w, intrinsics, dist, [f"r_{i}" for i in range(n_images)], width, height,
                 fisheye=lens == "fisheye")


def _kernel_rays(split: Split, n: int, seed: int):
    """(pixels [n, 3] int32, rays_d [n, 3]) from the Warp batch kernel, one ray per pixel."""
    out = [torch.empty(n, 3) for _ in range(4)]
    pixels = torch.empty(n, 3, dtype=torch.int32)
    _wp.launch(K.sample_pixels, n,
               [seed, 1, len(split), split.width, split.height, 3, split.lens_model, split.images.view(-1),
                torch.ones(1, dtype=torch.uint8), 0, split.c2w.reshape(-1).contiguous(), split.intrinsics,
                split.distortion, pixels, *out], "cpu")
    return pixels, out[1]


@pytest.mark.parametrize("lens", ["pinhole", "opencv", "fisheye"])
def test_kernel_rays_match_the_float64_twin(lens):
    split = _split(lens)
    assert split.lens_model == {"pinhole": LENS_PINHOLE, "opencv": LENS_OPENCV, "fisheye": LENS_FISHEYE}[lens]
    pixels, rays_d = _kernel_rays(split, 3000, seed=11)
    k, px, py = pixels.long().unbind(-1)
    dist = split.distortion[k].double() if split.has_distortion else None
    _, want = generate_rays(split.c2w[k].double(), split.intrinsics[k].double(), dist, px, py, fisheye=split.fisheye)
    # the corners are far off axis: the lens terms are not negligible there
    assert lens == "pinhole" or (want - generate_rays(split.c2w[k].double(), split.intrinsics[k].double(),
                                                      None, px, py)[1]).norm(dim=-1).max() > 1e-2
    torch.testing.assert_close(rays_d.double(), want, rtol=0, atol=2e-6)
    if lens == "pinhole":  # bit for bit what the float32 torch path computes
        _, want32 = split.rays(k, px, py)
        torch.testing.assert_close(rays_d, want32, rtol=0, atol=1e-6)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
@pytest.mark.parametrize("lens", ["pinhole", "opencv", "fisheye"])
def test_view_rays_match_the_float64_twin_row_by_row(lens, device):
    split = _split(lens)
    c2w, intr = split.c2w[3], split.intrinsics[3]
    dist = split.distortion[3] if split.has_distortion else None
    width, height, shift = split.width, split.height, (0.25, -0.125)
    o, d = view_rays(c2w, intr, dist, width, height, device, fisheye=split.fisheye, shift=shift)
    assert o.device.type == device and d.shape == (width * height, 3) and d.dtype == torch.float32
    pixel = torch.arange(width * height)
    px, py = (pixel % width).double() + shift[0], (pixel // width).double() + shift[1]
    n = width * height
    want_o, want_d = generate_rays(c2w.double().expand(n, 3, 4), intr.double().expand(n, 4),
                                   None if dist is None else dist.double().expand(n, 6), px, py, fisheye=split.fisheye)
    torch.testing.assert_close(o.cpu().double(), want_o, rtol=0, atol=1e-6)
    torch.testing.assert_close(d.cpu().double(), want_d, rtol=0, atol=2e-6)
    with pytest.raises(ValueError, match="fisheye"):
        view_rays(c2w, intr, None, width, height, device, fisheye=True)


@pytest.mark.parametrize("lens", ["pinhole", "opencv", "fisheye"])
def test_split_camera_gives_a_views_render_keywords(lens):
    split = _split(lens)
    cam = split.camera(3)
    assert (cam["width"], cam["height"], cam["fisheye"]) == (split.width, split.height, lens == "fisheye")
    assert torch.equal(cam["c2w"], split.c2w[3]) and torch.equal(cam["intrinsics"], split.intrinsics[3])
    if lens == "pinhole":
        assert cam["distortion"] is None
    else:
        assert torch.equal(cam["distortion"], split.distortion[3])
