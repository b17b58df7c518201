"""The march on a contracted occupancy grid against the float64 dense sampler."""

import pytest
import torch

from ngp_warp import MarchOptions, OccupancyGrid, ray_marching
from ngp_warp._reference import contraction as contraction_ref
from ngp_warp._reference import raymarch as raymarch_ref
from test_raymarch import MARGIN

FAR = 1000.0  # normalised distance ~250: C(x) within 0.005 of the boundary

INNER = [-4.0, -3.0, -4.0, 4.0, 5.0, 4.0]  # a non-cubic, off-centre inner box


def contracted_grid(kind, occupancy, resolution=16):
    grid = OccupancyGrid(torch.tensor(INNER), resolution=resolution, contraction=kind)
    if occupancy == "random":
        grid.occs.copy_((torch.rand(grid.n_cells) < 0.3).float())
        grid.threshold.fill_(0.5)
        grid._pack()
    else:  # a ground plane near z = -2 and a far shell, both set through world-space densities
        grid.update(0, lambda p: (((p[:, 2] + 2).abs() < 0.6) | (p.norm(dim=-1) > 40)).float())
    return grid


def match_dense(samples, dense, rtol=1e-4):
    """Index into the dense table of each emitted sample (asserting one matches its interval)."""
    key_dense = dense["ray"].double() * 4 * FAR + dense["t_start"]
    key = samples.ray_indices.double() * 4 * FAR + samples.t_starts.double()
    pos = torch.searchsorted(key_dense, key).clamp(1, key_dense.numel() - 1)
    pos = torch.where((key - key_dense[pos - 1]).abs() < (key - key_dense[pos]).abs(), pos - 1, pos)
    err = (key - key_dense[pos]).abs()
    assert (err <= rtol * (1 + samples.t_starts.double())).all(), err.max()
    torch.testing.assert_close(samples.t_ends.double(), dense["t_end"][pos], rtol=rtol, atol=1e-5)
    return pos


def camera_rays(n):
    """Rays from inside the inner box in every direction, and from outside it."""
    o_in = torch.rand(n, 3) * 4 - 2
    o_out = torch.nn.functional.normalize(torch.randn(n // 4, 3), dim=-1) * 30
    d = torch.nn.functional.normalize(torch.randn(n + n // 4, 3), dim=-1)
    return torch.cat([o_in, o_out]).contiguous(), d.contiguous()


@pytest.mark.parametrize("kind", ["l2", "linf"])
@pytest.mark.parametrize("occupancy", ["random", "surfaces"])
@pytest.mark.parametrize("cone_angle", [0.0, 1 / 256])
def test_contracted_march_matches_dense_sampler(kind, occupancy, cone_angle):
    torch.manual_seed(3)
    grid = contracted_grid(kind, occupancy)
    rays_o, rays_d = camera_rays(120)
    kw = dict(near=0.05, far=FAR, cone_angle=cone_angle, max_step=0.5)
    step = grid.default_step_size * 4
    samples = ray_marching(rays_o, rays_d, grid, MarchOptions(step_size=step, **kw))
    dense = raymarch_ref.ray_marching_contracted(rays_o, rays_d, INNER, kind, grid.occupied(), step=step, **kw)
    pos = match_dense(samples, dense)
    sure = dense["margin"] > MARGIN
    assert (dense["occupied"][pos] | ~sure[pos]).all()  # every sample lies in an occupied cell
    emitted = torch.zeros_like(sure)
    emitted[pos] = True
    required = dense["occupied"] & sure
    assert (emitted | ~required).all(), f"{int((required & ~emitted).sum())} occupied samples skipped"
    assert required.sum() > 300 and (~sure).float().mean() < 0.01
    mid = rays_o.double()[samples.ray_indices] + rays_d.double()[samples.ray_indices] * (
        0.5 * (samples.t_starts + samples.t_ends)).double()[:, None]
    torch.testing.assert_close(samples.positions.double(), mid, rtol=1e-5, atol=1e-5)
    # world steps are long far out yet span about `step` once contracted
    far = dense["t_start"][pos] > 100
    assert far.any() and (samples.t_ends - samples.t_starts)[far].min() > 1.0
    y = contraction_ref.contract(samples.positions.double(), kind, torch.tensor(INNER))
    radius = torch.linalg.vector_norm(y, ord=2 if kind == "l2" else float("inf"), dim=-1)
    assert 1.99 < radius.max() < 2.0


def test_contracted_march_ends_and_covers_every_ray():
    grid = OccupancyGrid(torch.tensor(INNER), resolution=8, contraction="l2")  # fresh: all occupied
    rays_o, rays_d = camera_rays(40)
    samples = ray_marching(rays_o, rays_d, grid, MarchOptions(near=0.1))
    counts = samples.ray_offsets.diff()
    assert (counts > 100).all() and (counts < 2000).all()  # the contracted length of a ray is finite
    first = samples.t_starts[samples.ray_offsets[:-1].long()]
    torch.testing.assert_close(first, torch.full_like(first, 0.1))
    stratified = ray_marching(rays_o, rays_d, grid, MarchOptions(near=0.1, stratified=True))
    assert not torch.equal(stratified.t_starts[:100], samples.t_starts[:100])


def test_contracted_grid_checks():
    with pytest.raises(ValueError, match="one cascade"):
        OccupancyGrid(torch.tensor(INNER), resolution=8, levels=2, contraction="l2")
    with pytest.raises(ValueError, match="contraction must be"):
        OccupancyGrid(torch.tensor(INNER), resolution=8, contraction="sphere")
