"""Issue 22 item 7: the public ops refuse inputs that would render wrong numbers silently."""

import pytest
import torch

from ngp_warp import OccupancyGrid, composite, ray_marching, render_rays

AABB = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]


def rays(n: int = 64, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    o = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1) * 3.0
    d = torch.nn.functional.normalize(torch.rand(n, 3, generator=g) * 0.4 - 0.2 - o, dim=-1)
    return o, d


def field(positions, directions):
    sigma = 20.0 * (positions.norm(dim=-1) < 0.6).float() + 0.1
    return sigma, torch.sigmoid(positions)


def grid() -> OccupancyGrid:
    return OccupancyGrid(AABB, resolution=16)


def test_render_rays_rejects_non_unit_directions_and_nan_origins():
    o, d = rays()
    ok = render_rays(o, d, grid(), field)
    assert ok["opacity"].max() > 0.9
    with pytest.raises(ValueError, match="not unit vectors"):
        render_rays(o, d * 0.5, grid(), field)
    bad_o = o.clone()
    bad_o[7, 1] = float("nan")
    with pytest.raises(ValueError, match="NaN or infinite origins"):
        render_rays(bad_o, d, grid(), field)
    bad_d = d.clone()
    bad_d[3] = float("inf")
    with pytest.raises(ValueError, match="NaN or infinite directions"):
        ray_marching(o, bad_d, grid())
    # ray_marching measures t in units of |d|: scaled directions are allowed there
    assert ray_marching(o, d * 0.5, grid()).n_samples > 0
    # validate=False skips the checks (the trainer's own rays)
    render_rays(o, d * 0.5, grid(), field, validate=False)


def test_render_rays_rejects_negative_or_nan_sigmas_from_the_field_and_sigma_fn():
    o, d = rays()

    def negative(positions, directions):
        sigmas, rgbs = field(positions, directions)
        return sigmas - 1.0, rgbs

    with pytest.raises(ValueError, match="field_fn returned negative or NaN sigmas"):
        render_rays(o, d, grid(), negative)
    with pytest.raises(ValueError, match="sigma_fn returned negative"):
        render_rays(o, d, grid(), field, sigma_fn=lambda x: torch.full((x.shape[0],), float("nan")))
    render_rays(o, d, grid(), negative, validate=False)  # unchecked on request


def packed(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    n_rays, per_ray = 8, 5
    idx = torch.arange(n_rays).repeat_interleave(per_ray)
    t0 = torch.rand(idx.shape[0], generator=g)
    sigmas = torch.rand(idx.shape[0], generator=g) * 4 + 0.1
    rgbs = torch.rand(idx.shape[0], 3, generator=g)
    return sigmas, rgbs, t0, t0 + 0.3, idx, n_rays


@pytest.mark.parametrize("problem, match", [
    ("unsorted", "sorted"), ("out_of_range", r"\[0, n_rays\)"), ("negative_index", r"\[0, n_rays\)"),
    ("t_ends_before_starts", "t_ends ≥ t_starts"), ("nan_t", "finite"), ("negative_sigma", "sigmas must be"),
])
def test_composite_rejects_malformed_samples(problem, match):
    sigmas, rgbs, t0, t1, idx, n_rays = packed()
    composite(sigmas, rgbs, t0, t1, idx, n_rays)  # the good samples pass
    if problem == "unsorted":
        idx = idx.clone()
        idx[[3, 30]] = idx[[30, 3]]
    elif problem == "out_of_range":
        idx = idx.clone()
        idx[-1] = n_rays
    elif problem == "negative_index":
        idx = idx.clone()
        idx[0] = -1
    elif problem == "t_ends_before_starts":
        t1 = t1.clone()
        t1[4] = t0[4] - 0.1
    elif problem == "nan_t":
        t0 = t0.clone()
        t0[2] = float("nan")
    else:
        sigmas = sigmas.clone()
        sigmas[9] = -2.0
    with pytest.raises(ValueError, match=match):
        composite(sigmas, rgbs, t0, t1, idx, n_rays)
    composite(sigmas, rgbs, t0, t1, idx.clamp(0, n_rays - 1), n_rays, validate=False)  # unchecked on request


def test_validated_composite_equals_unvalidated():
    sigmas, rgbs, t0, t1, idx, n_rays = packed(1)
    for a, b in zip(composite(sigmas, rgbs, t0, t1, idx, n_rays),
                    composite(sigmas, rgbs, t0, t1, idx, n_rays, validate=False)):
        assert torch.equal(a, b)
