"""Pruning marched samples to those that composite: exact against a float64 twin, fixed-capacity
packing, and renders (values and gradients) unchanged by it."""

import pytest
import torch

from ngp_warp import MarchOptions, prune_samples, render_rays
from ngp_warp._reference import prune as prune_ref
from ngp_warp.ops.raymarch import RaySamples

from test_render import camera_rays, sphere_field, sphere_grid


def random_samples(n_rays=40, seed=0, device="cpu") -> tuple[RaySamples, torch.Tensor]:
    """Rays with 0..30 samples of random lengths and densities spanning empty to opaque."""
    g = torch.Generator().manual_seed(seed)
    counts = torch.randint(0, 31, (n_rays,), generator=g)
    offsets = torch.zeros(n_rays + 1, dtype=torch.int32)
    offsets[1:] = counts.cumsum(0)
    n = int(offsets[-1])
    ray_indices = torch.repeat_interleave(torch.arange(n_rays), counts)
    t_starts = torch.rand(n, generator=g) * 3
    t_ends = t_starts + 0.01 + 0.1 * torch.rand(n, generator=g)
    sigmas = torch.rand(n, generator=g) ** 3 * 60
    positions, directions = torch.rand(n, 3, generator=g), torch.rand(n, 3, generator=g)
    s = RaySamples(ray_indices, t_starts, t_ends, positions, directions, offsets)
    s = RaySamples(*(t.to(device) for t in (s.ray_indices, s.t_starts, s.t_ends, s.positions, s.directions,
                                           s.ray_offsets)))
    return s, sigmas.to(device)


def test_keeps_exactly_the_samples_that_composite():
    samples, sigmas = random_samples()
    eps = 1e-2
    keep, trans = prune_ref.prune_samples(sigmas, samples.t_starts, samples.t_ends, samples.ray_indices, 40, eps)
    assert 0.2 < keep.float().mean() < 0.8  # the test prunes something and keeps something
    clear = (trans.log() - torch.log(torch.tensor(eps, dtype=torch.float64))).abs() > 1e-4
    assert clear.float().mean() > 0.99

    out = prune_samples(samples, sigmas, eps)
    got = out.samples
    assert got.n_samples == int(keep.sum()) == int(out.n_contributing)
    assert out.ray_mask.all()
    torch.testing.assert_close(got.ray_offsets[1:].long(),
                               torch.zeros(40, dtype=torch.long).index_add_(0, samples.ray_indices[keep],
                                                                          torch.ones(int(keep.sum()), dtype=torch.long)).cumsum(0))
    for name in ("ray_indices", "t_starts", "t_ends", "positions", "directions"):
        assert torch.equal(getattr(got, name), getattr(samples, name)[keep]), name


def test_capacity_packs_a_fixed_buffer_and_drops_rays_that_do_not_fit():
    samples, sigmas = random_samples(seed=1)
    full = prune_samples(samples, sigmas, 1e-2)
    total = full.samples.n_samples
    for capacity in (1, total // 2, total + 37):  # 1: only ray 0 (one contributing sample) fits
        out = prune_samples(samples, sigmas, 1e-2, capacity=capacity, pad_position=(0.5, 0.25, 0.75))
        s = out.samples
        assert s.n_samples == capacity and int(out.n_contributing) == total
        ends = full.samples.ray_offsets[1:]
        fits = ends <= capacity  # a prefix of the rays fits whole
        kept_rays = int(fits.sum())
        assert fits[:kept_rays].all() and not fits[kept_rays:].any()
        empty = torch.diff(full.samples.ray_offsets) == 0
        assert torch.equal(out.ray_mask, fits | empty)  # rays without samples lose nothing
        assert capacity > total or (empty[kept_rays:].any() and not out.ray_mask[kept_rays:].all())
        end = int(s.ray_offsets[-1])
        assert end == int(full.samples.ray_offsets[kept_rays]) <= capacity
        assert torch.equal(s.ray_offsets, full.samples.ray_offsets.clamp(max=end))
        assert capacity < total or kept_rays == 40
        assert capacity >= total or end + int(full.samples.ray_offsets[kept_rays + 1] - full.samples.ray_offsets[kept_rays]) > capacity
        assert torch.equal(s.t_starts[:end], full.samples.t_starts[:end])
        assert torch.equal(s.positions[:end], full.samples.positions[:end])
        pad = slice(end, capacity)
        assert (s.ray_indices[pad] == 40).all() and not s.t_starts[pad].any() and not s.t_ends[pad].any()
        assert torch.equal(s.positions[pad], torch.tensor([0.5, 0.25, 0.75]).expand(capacity - end, 3))


def test_capacity_below_the_first_ray_and_no_rays():
    samples, sigmas = random_samples(seed=1)
    sigmas = torch.full_like(sigmas, 1e-3)  # nearly empty: every sample of every ray contributes
    counts = torch.diff(samples.ray_offsets)
    first = int((counts > 0).int().argmax())  # the first ray with samples: more than one of them
    assert counts[first] > 1
    out = prune_samples(samples, sigmas, 1e-2, capacity=int(counts[first]) - 1)
    assert not out.samples.ray_offsets.any()  # no ray fits: every row is padding
    assert torch.equal(out.ray_mask, counts == 0)
    empty = RaySamples(*(t[:0] for t in (samples.ray_indices, samples.t_starts, samples.t_ends, samples.positions,
                                          samples.directions)), torch.zeros(1, dtype=torch.int32))
    out = prune_samples(empty, sigmas[:0], 1e-2, capacity=4)
    assert out.ray_mask.shape == (0,) and out.samples.ray_offsets.tolist() == [0]
    assert int(out.n_contributing) == 0 and (out.samples.ray_indices == 0).all()


def test_render_with_sigma_fn_gives_the_same_pixels_and_gradients():
    grid = sphere_grid(16)
    rays_o, rays_d = camera_rays(64)
    scale = torch.tensor(5.0, requires_grad=True)  # opaque enough that rays stop inside
    tint = torch.tensor([0.9, 0.4, 0.2], requires_grad=True)

    def field(positions, directions):
        sigma, _ = sphere_field(positions, directions)
        return sigma * scale * (1 + positions[:, 0]), torch.sigmoid(positions * 2 + directions) * tint

    def run(**kw):
        scale.grad = tint.grad = None
        out = render_rays(rays_o, rays_d, grid, field, MarchOptions(step_size=0.01), early_stop_eps=1e-3,
                          background=0.5, **kw)
        (out["rgb"].sum() + out["depth"].sum() * 0.3).backward()
        return out, scale.grad.clone(), tint.grad.clone()

    plain, *plain_grads = run()
    sigma_fn = lambda p: field(p, torch.zeros_like(p))[0]  # noqa: E731
    n_marched = plain["n_samples"]
    for capacity in (None, n_marched):
        pruned, *grads = run(sigma_fn=sigma_fn, sample_capacity=capacity)
        assert pruned["n_marched"] == n_marched and pruned["ray_mask"].all()
        assert int(pruned["n_contributing"]) < 0.7 * n_marched  # rays through the sphere stop early
        for key in ("rgb", "opacity", "depth"):
            torch.testing.assert_close(pruned[key], plain[key], rtol=1e-5, atol=1e-6)
        for a, b in zip(grads, plain_grads):
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("kwargs", [
    {"sigmas": torch.ones(3)}, {"sigmas": "double"}, {"capacity": 0}, {"early_stop_eps": -1.0},
])
def test_invalid_inputs_raise_value_error(kwargs):
    samples, sigmas = random_samples(4)
    if kwargs.get("sigmas") == "double":
        kwargs["sigmas"] = sigmas.double()
    with pytest.raises(ValueError):
        prune_samples(samples, **{"sigmas": sigmas, **kwargs})


def test_sample_capacity_needs_a_sigma_fn():
    grid = sphere_grid(8)
    rays_o, rays_d = camera_rays(4)
    with pytest.raises(ValueError, match="sigma_fn"):
        render_rays(rays_o, rays_d, grid, sphere_field, MarchOptions(step_size=0.05), sample_capacity=100)


@pytest.mark.cuda
def test_cuda_matches_cpu():
    cpu_s, cpu_sigmas = random_samples(seed=2)
    cuda_s, cuda_sigmas = random_samples(seed=2, device="cuda")
    for capacity in (None, 150):
        a = prune_samples(cpu_s, cpu_sigmas, 1e-2, capacity=capacity)
        b = prune_samples(cuda_s, cuda_sigmas, 1e-2, capacity=capacity)
        assert torch.equal(a.ray_mask, b.ray_mask.cpu()) and torch.equal(a.n_contributing, b.n_contributing.cpu())
        for name in ("ray_offsets", "ray_indices", "t_starts", "positions"):
            assert torch.equal(getattr(a.samples, name), getattr(b.samples, name).cpu()), name
