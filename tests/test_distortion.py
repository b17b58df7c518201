"""Distortion loss: values and gradients against its float64 twin, padding rows, bad input."""

import pytest
import torch

from ngp_warp import composite
from ngp_warp._reference import composite as composite_ref
from ngp_warp._reference import distortion as distortion_ref
from ngp_warp.ops.distortion import distortion_loss, distortion_loss_packed


def packed_samples(counts, n_padding=0, seed=0):
    """Random weights on sorted intervals at camera-like distances (t ≈ 4), rays of the given
    sample counts (0 allowed), then ``n_padding`` rows of ray index len(counts) with zero weight."""
    g = torch.Generator().manual_seed(seed)
    n_rays = len(counts)
    starts, ends, rays = [], [], []
    for r, c in enumerate(counts):
        t0 = 3.5 + torch.rand(1, generator=g)
        widths = 0.005 + 0.02 * torch.rand(c, generator=g)
        gaps = 0.03 * torch.rand(c, generator=g) * (torch.rand(c, generator=g) < 0.3)  # skipped space
        s = t0 + torch.cumsum(widths + gaps, 0) - widths
        starts.append(s)
        ends.append(s + widths)
        rays.append(torch.full((c,), r))
    rays.append(torch.full((n_padding,), n_rays))
    ts = torch.cat(starts + [torch.zeros(n_padding)]).float()
    te = torch.cat(ends + [torch.zeros(n_padding)]).float()
    w = torch.rand(ts.shape[0], generator=g) / 8
    if n_padding:
        w[-n_padding:] = 0.0
    return w.float(), ts, te, torch.cat(rays).long(), n_rays


COUNTS = [5, 0, 1, 17, 40, 3, 0, 64]


# near 3.6 maps t to s = 1 − 3.6/t, with some samples (t from 3.5) clamped to s = 0
@pytest.mark.parametrize("near", [0.0, 3.6])
def test_values_match_the_float64_twin(near):
    w, ts, te, rays, n = packed_samples(COUNTS)
    ours = distortion_loss(w, ts, te, rays, n, near=near)
    ref = distortion_ref.distortion_loss(w, ts, te, rays, n, near=near)
    assert ref.abs().max() > (1e-3 if near == 0 else 1e-5) and (ref[[1, 6]] == 0).all()
    torch.testing.assert_close(ours.double(), ref, rtol=1e-4, atol=1e-7 if near == 0 else 1e-9)


@pytest.mark.parametrize("near", [0.0, 3.6])
def test_gradients_match_the_float64_twin(near):
    w, ts, te, rays, n = packed_samples(COUNTS, seed=1)
    upstream = torch.randn(n)
    w1 = w.clone().requires_grad_(True)
    (distortion_loss(w1, ts, te, rays, n, near=near) * upstream).sum().backward()
    w2 = w.double().clone().requires_grad_(True)
    (distortion_ref.distortion_loss(w2, ts, te, rays, n, near=near) * upstream.double()).sum().backward()
    assert w2.grad.abs().max() > (1e-3 if near == 0 else 1e-4)
    torch.testing.assert_close(w1.grad.double(), w2.grad, rtol=1e-4, atol=1e-6 if near == 0 else 1e-8)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
@pytest.mark.parametrize("near", [0.0, 4.0])
def test_interval_gradients_match_the_float64_twin(near, device):
    w, ts, te, rays, n = packed_samples(COUNTS)  # with near 4 some samples lie before it: no gradient
    across = int(((ts < 4.0) & (te > 4.0)).nonzero()[0])
    ts[across] = 4.0  # one starts at the near itself, as a march's first sample does: s' = 1/near there
    upstream = torch.randn(n)
    s1, e1 = ts.clone().requires_grad_(True), te.clone().requires_grad_(True)
    (distortion_loss(w.to(device), s1.to(device), e1.to(device), rays.to(device), n, near=near)
     * upstream.to(device)).sum().backward()
    s2, e2 = ts.double().requires_grad_(True), te.double().requires_grad_(True)
    (distortion_ref.distortion_loss(w.double(), s2, e2, rays, n, near=near) * upstream.double()).sum().backward()
    assert e2.grad.abs().max() > (1e-3 if near == 0 else 1e-4) and (s2.grad == 0).any() == (near > 0)
    for ours, twin in ((s1.grad, s2.grad), (e1.grad, e2.grad)):
        torch.testing.assert_close(ours.double(), twin, rtol=1e-3, atol=1e-6 if near == 0 else 1e-7)


def test_normalised_distance_weighs_spread_near_the_camera_more():
    # two rays with the same world-space spread: weight at t = 1 and 2, or at t = 10 and 11
    ts = torch.tensor([1.0, 2.0, 10.0, 11.0])
    w, rays = torch.full((4,), 0.5), torch.tensor([0, 0, 1, 1])
    world = distortion_loss(w, ts, ts + 0.01, rays, 2)
    normalised = distortion_loss(w, ts, ts + 0.01, rays, 2, near=0.5)
    torch.testing.assert_close(world[0], world[1])
    assert normalised[0] > 20 * normalised[1]


def test_padding_rows_are_ignored_and_get_no_gradient():
    w, ts, te, rays, n = packed_samples(COUNTS, n_padding=7, seed=2)
    w[-7:] = 0.3  # even with weight, a row past the last ray belongs to no ray
    w.requires_grad_(True)
    loss = distortion_loss(w, ts, te, rays, n)
    torch.testing.assert_close(loss.double(), distortion_ref.distortion_loss(w, ts, te, rays, n), rtol=1e-4, atol=1e-7)
    loss.sum().backward()
    assert (w.grad[-7:] == 0).all() and w.grad[:-7].abs().max() > 0


def test_packed_offsets_give_the_same_loss_and_gradients():
    w, ts, te, rays, n = packed_samples(COUNTS, n_padding=3, seed=5)
    upstream = torch.randn(n)
    by_index, by_offset = w.clone().requires_grad_(True), w.clone().requires_grad_(True)
    a = distortion_loss(by_index, ts, te, rays, n)
    b = distortion_loss_packed(by_offset, ts, te, composite_ref.ray_offsets_from_indices(rays, n).int())
    assert a.abs().max() > 0
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    (a * upstream).sum().backward()
    (b * upstream).sum().backward()
    torch.testing.assert_close(by_index.grad, by_offset.grad, rtol=0, atol=0)


def test_a_crisp_ray_costs_less_than_a_spread_one():
    # Equal opacity: all of it in one short interval versus spread over eight.
    ts = torch.tensor([4.0, 4.01, 4.02, 4.03, 4.04, 4.05, 4.06, 4.07] * 2)
    te = ts + 0.01
    w = torch.tensor([0.0, 0.0, 0.8, 0.0, 0.0, 0.0, 0.0, 0.0] + [0.1] * 8)
    loss = distortion_loss(w, ts, te, torch.tensor([0] * 8 + [1] * 8), 2)
    assert loss[0] < loss[1] / 5


def test_trains_through_composite_to_the_densities():
    w, ts, te, rays, n = packed_samples([6, 9], seed=3)
    sigmas = torch.full_like(ts, 20.0, requires_grad=True)
    rgbs = torch.rand(ts.shape[0], 3)
    *_, weights = composite(sigmas, rgbs, ts, te, rays, n, return_weights=True)
    distortion_loss(weights, ts, te, rays, n).sum().backward()
    assert torch.isfinite(sigmas.grad).all() and sigmas.grad.abs().max() > 0


@pytest.mark.parametrize("bad, match", [
    (dict(weights=torch.zeros(3, dtype=torch.float64)), "weights must be"),
    (dict(t_ends=torch.zeros(2)), "t_ends must be"),
    (dict(ray_indices=torch.zeros(3, dtype=torch.int32)), "ray_indices must be"),
    (dict(n_rays=-1), "n_rays"),
    (dict(near=-1.0), "near must be"),
    (dict(near=float("nan")), "near must be"),
])
def test_rejects_bad_input(bad, match):
    args = dict(weights=torch.zeros(3), t_starts=torch.zeros(3), t_ends=torch.ones(3),
                ray_indices=torch.zeros(3, dtype=torch.int64), n_rays=1)
    with pytest.raises(ValueError, match=match):
        distortion_loss(**{**args, **bad})


@pytest.mark.cuda
@pytest.mark.parametrize("near", [0.0, 3.6])
def test_cuda_matches_cpu(near):
    w, ts, te, rays, n = packed_samples(COUNTS * 50, n_padding=5, seed=4)
    cpu_w = w.clone().requires_grad_(True)
    gpu_w = w.cuda().requires_grad_(True)
    cpu = distortion_loss(cpu_w, ts, te, rays, n, near=near)
    gpu = distortion_loss(gpu_w, ts.cuda(), te.cuda(), rays.cuda(), n, near=near)
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-5, atol=1e-7)
    upstream = torch.randn(n)
    (cpu * upstream).sum().backward()
    (gpu * upstream.cuda()).sum().backward()
    torch.testing.assert_close(gpu_w.grad.cpu(), cpu_w.grad, rtol=1e-5, atol=1e-6)
