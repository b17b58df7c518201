import pytest
import torch

from ngp_warp import MarchOptions, OccupancyGrid, ray_marching, render_rays
from ngp_warp._reference import composite as composite_ref
from ngp_warp._reference import render as render_ref

AABB = torch.tensor([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0])
CENTER = torch.tensor([0.1, -0.05, 0.0])
RADIUS, SIGMA = 0.6, 4.0
COLOR = torch.tensor([0.2, 0.5, 0.8])


def sphere_field(positions, directions):
    inside = ((positions - CENTER.to(positions.device)) ** 2).sum(-1) < RADIUS**2
    return SIGMA * inside.float(), COLOR.to(positions.device).expand(positions.shape[0], 3)


def sphere_grid(resolution=32, device="cpu"):
    """Grid whose occupied cells cover the sphere (density_fn padded by a cell diagonal)."""
    grid = OccupancyGrid(AABB, resolution=resolution).to(device)
    pad = 2.0 / resolution * 3**0.5
    grid.update(0, lambda p: (((p - CENTER.to(p.device)) ** 2).sum(-1) < (RADIUS + pad) ** 2).float())
    return grid


def camera_rays(n, device="cpu"):
    """Rays from a sphere of radius 3 aimed at points around the sphere (some miss it)."""
    o = torch.nn.functional.normalize(torch.randn(n, 3), dim=-1) * 3.0
    aim = CENTER + (torch.rand(n, 3) * 2 - 1) * 0.7
    d = torch.nn.functional.normalize(aim - o, dim=-1)
    return o.to(device), d.to(device)


def check_sphere(out, rays_o, rays_d, step):
    opacity, depth = render_ref.render_rays(rays_o, rays_d, CENTER, RADIUS, SIGMA)
    assert 40 < (opacity > 0).sum() < 250
    # Midpoint sampling misplaces each end of the chord by at most step/2, so the optical depth
    # is off by at most σ·step and the depth by at most that times the exit distance (≤ 4).
    err_o = out["opacity"].cpu().double() - opacity
    err_d = out["depth"].cpu().double() - depth
    assert err_o.abs().max() <= SIGMA * step and err_d.abs().max() <= 4 * SIGMA * step
    assert abs(err_o.mean()) < 5e-4  # no bias
    hit = opacity > 0.2
    err_mean_t = (out["depth"] / out["opacity"]).cpu().double()[hit] - (depth / opacity)[hit]
    assert err_mean_t.abs().max() < step and abs(err_mean_t.mean()) < 0.1 * step
    torch.testing.assert_close(out["rgb"].cpu(), out["opacity"].cpu()[:, None] * COLOR, rtol=1e-5, atol=1e-6)


def test_sphere_opacity_and_depth_match_closed_form():
    grid = sphere_grid()
    rays_o, rays_d = camera_rays(256)
    out = render_rays(rays_o, rays_d, grid, sphere_field, MarchOptions(near=0.0, far=10.0, step_size=2e-3),
                      early_stop_eps=0.0)
    check_sphere(out, rays_o, rays_d, 2e-3)
    assert grid.occupied().float().mean() < 0.25 and out["n_samples"] < 256 * 700


def test_gradients_reach_the_field_like_a_float64_pipeline():
    grid = sphere_grid(16)
    rays_o, rays_d = camera_rays(64)
    scale = torch.tensor(1.5, requires_grad=True)
    tint = torch.tensor([0.9, 0.4, 0.2], requires_grad=True)

    def field(positions, directions):
        sigma, _ = sphere_field(positions, directions)
        return sigma * scale * (1 + positions[:, 0]), torch.sigmoid(positions * 2 + directions) * tint

    bg = torch.rand(64, 3)
    out = render_rays(rays_o, rays_d, grid, field, MarchOptions(step_size=0.01), background=bg)
    (out["rgb"].sum() + out["depth"].sum() * 0.3).backward()
    grads = scale.grad.clone(), tint.grad.clone()

    scale.grad = tint.grad = None
    s = ray_marching(rays_o, rays_d, grid, MarchOptions(step_size=0.01))
    sigmas, rgbs = field(s.positions.double(), s.directions.double())
    rgb, opacity, depth, _ = composite_ref.composite(sigmas, rgbs, s.t_starts, s.t_ends, s.ray_indices, 64, 1e-4)
    ((rgb + bg * (1 - opacity[:, None])).sum() + depth.sum() * 0.3).backward()
    torch.testing.assert_close(grads[0], scale.grad, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(grads[1], tint.grad, rtol=1e-4, atol=1e-6)
    assert grads[0].abs() > 1e-3


def blob_field(positions, directions):
    """A smooth field (σ and colour vary with position everywhere), so that positions get gradients."""
    sigma = 6.0 * torch.exp(-((positions - CENTER.to(positions.device)) ** 2).sum(-1) / 0.3)
    return sigma, torch.sigmoid(positions * 2 + directions)


@pytest.mark.parametrize("pruned", [False, True])
def test_gradients_reach_rays_that_require_them_like_a_float64_pipeline(pruned):
    grid = sphere_grid(16)
    rays_o, rays_d = camera_rays(64)
    o, d = rays_o.clone().requires_grad_(True), rays_d.clone().requires_grad_(True)
    march = MarchOptions(step_size=0.01)
    prune = dict(sigma_fn=lambda x: blob_field(x, x)[0], sample_capacity=20000) if pruned else {}
    out = render_rays(o, d, grid, blob_field, march, background=0.5, return_samples=True, **prune)
    assert out["n_samples"] > 1000
    (out["rgb"] * torch.tensor([1.0, -0.5, 0.3])).sum().backward()

    # float64: the same samples (distances fixed), positions o + t d, directions d
    n = out["ray_offsets"][-1]  # padding rows past it
    ri, t = out["ray_indices"][:n], (0.5 * (out["t_starts"] + out["t_ends"]))[:n].double()
    o64, d64 = rays_o.double().requires_grad_(True), rays_d.double().requires_grad_(True)
    sigmas, rgbs = blob_field(o64[ri] + t[:, None] * d64[ri], d64[ri])
    rgb, opacity, _, _ = composite_ref.composite(sigmas, rgbs, out["t_starts"][:n], out["t_ends"][:n], ri, 64, 1e-4)
    ((rgb + 0.5 * (1 - opacity[:, None])) * torch.tensor([1.0, -0.5, 0.3], dtype=torch.float64)).sum().backward()
    torch.testing.assert_close(o.grad, o64.grad.float(), rtol=2e-3, atol=2e-5)
    torch.testing.assert_close(d.grad, d64.grad.float(), rtol=2e-3, atol=2e-5)
    assert o.grad.abs().max() > 1e-2 and d.grad.abs().max() > 1e-2


def test_near_gradient_scaling_scales_each_samples_gradient_by_its_squared_distance():
    grid = sphere_grid(16)
    rays_o, rays_d = camera_rays(64)
    rays_o = rays_o * 0.8  # origins at 2.4, the sphere's near side at about 1.8: scales from ~0.4 to 1
    amount = torch.tensor(1.3, requires_grad=True)

    def field(positions, directions):
        sigma, rgb = blob_field(positions, directions)
        return sigma * amount, rgb * amount

    values = []
    for distance in (0.0, 2.5):
        out = render_rays(rays_o, rays_d, grid, field, MarchOptions(step_size=0.01), near_gradient_distance=distance,
                          return_samples=True)
        (out["rgb"] * torch.tensor([1.0, -0.5, 0.3])).sum().backward()
        values.append((out["rgb"].detach(), amount.grad.clone()))
        amount.grad = None
    torch.testing.assert_close(values[0][0], values[1][0], rtol=0, atol=0)  # values unchanged

    # float64: the same samples, each field output's gradient times min(1, (t / 2.5)²)
    s = ray_marching(rays_o, rays_d, grid, MarchOptions(step_size=0.01))
    scale = ((0.5 * (s.t_starts + s.t_ends)).double() / 2.5).square().clamp_max(1.0)
    sigmas, rgbs = field(s.positions.double(), s.directions.double())
    sigmas = sigmas * scale + (sigmas * (1 - scale)).detach()
    rgbs = rgbs * scale[:, None] + (rgbs * (1 - scale[:, None])).detach()
    rgb, _, _, _ = composite_ref.composite(sigmas, rgbs, s.t_starts, s.t_ends, s.ray_indices, 64, 1e-4)
    (rgb * torch.tensor([1.0, -0.5, 0.3], dtype=torch.float64)).sum().backward()
    torch.testing.assert_close(values[1][1], amount.grad.float(), rtol=1e-4, atol=1e-6)
    assert values[1][1].abs() < 0.9 * values[0][1].abs()  # the scaling took some of it away
    with pytest.raises(ValueError, match="near_gradient_distance"):
        render_rays(rays_o, rays_d, grid, field, near_gradient_distance=-1.0)


def test_rays_without_grad_leave_the_positions_alone():
    grid = sphere_grid(16)
    rays_o, rays_d = camera_rays(32)
    out = render_rays(rays_o, rays_d, grid, blob_field, MarchOptions(step_size=0.01), return_samples=True)
    s = ray_marching(rays_o, rays_d, grid, MarchOptions(step_size=0.01))
    torch.testing.assert_close(out["t_starts"], s.t_starts)
    assert not out["rgb"].requires_grad


def test_background_and_returned_samples():
    grid = sphere_grid(16)
    rays_o, rays_d = camera_rays(32)
    plain = render_rays(rays_o, rays_d, grid, sphere_field, MarchOptions(step_size=0.01), return_samples=True)
    per_ray = torch.zeros(32).index_add_(0, plain["ray_indices"], plain["weights"])
    torch.testing.assert_close(per_ray, plain["opacity"], rtol=1e-5, atol=1e-6)
    assert plain["ray_offsets"].dtype == torch.int32 and plain["ray_indices"].unique().numel() > 1
    assert torch.equal(plain["ray_offsets"].long(), composite_ref.ray_offsets_from_indices(plain["ray_indices"], 32))
    for bg in (0.25, torch.tensor([0.1, 0.2, 0.3]), torch.rand(32, 3)):
        out = render_rays(rays_o, rays_d, grid, sphere_field, MarchOptions(step_size=0.01), background=bg)
        expected = plain["rgb"] + torch.as_tensor(bg).expand(32, 3) * (1 - plain["opacity"])[:, None]
        torch.testing.assert_close(out["rgb"], expected)


def test_no_samples_returns_background_in_the_fields_graph():
    grid = sphere_grid(16)
    rays_o = torch.tensor([[0.0, 3.0, 0.0], [5.0, 5.0, 5.0]])
    rays_d = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    weight = torch.tensor(2.0, requires_grad=True)
    rows = []

    def field(positions, directions):
        rows.append(positions.shape[0])
        return weight * positions.sum(-1).abs(), weight * torch.sigmoid(directions)

    out = render_rays(rays_o, rays_d, grid, field, background=torch.tensor([0.3, 0.6, 0.9]), return_samples=True)
    assert out["n_samples"] == 0 and out["weights"].shape == (0,) and rows == [0]
    assert torch.equal(out["rgb"], torch.tensor([[0.3, 0.6, 0.9]] * 2)) and not out["opacity"].any()
    out["rgb"].sum().backward()  # a loss on a batch that missed everything still backpropagates
    assert weight.grad == 0
    with torch.no_grad():
        out = render_rays(rays_o, rays_d, grid, field, background=0.5)
    assert rows == [0] and torch.equal(out["rgb"], torch.full((2, 3), 0.5))  # not called without autograd


@pytest.mark.parametrize(
    "field, kwargs",
    [
        (lambda p, d: (torch.ones(p.shape[0], 2), torch.ones(p.shape[0], 3)), {}),
        (lambda p, d: (torch.ones(p.shape[0]), torch.ones(p.shape[0], 4)), {}),
        (sphere_field, {"background": torch.ones(5, 3)}),
        (sphere_field, {"early_stop_eps": -1.0}),
    ],
)
def test_invalid_inputs_raise_value_error(field, kwargs):
    grid = OccupancyGrid(AABB, resolution=8)
    rays_o, rays_d = camera_rays(4)
    with pytest.raises(ValueError):
        render_rays(rays_o, rays_d, grid, field, MarchOptions(step_size=0.05), **kwargs)


@pytest.mark.cuda
def test_cuda_sphere_matches_closed_form():
    rays_o, rays_d = camera_rays(256)
    grid = sphere_grid(device="cuda")
    out = render_rays(rays_o.cuda(), rays_d.cuda(), grid, sphere_field, MarchOptions(step_size=2e-3),
                      early_stop_eps=0.0)
    check_sphere(out, rays_o, rays_d, 2e-3)


def test_composite_export_stays_a_function_after_the_library_imports():
    import ngp_warp

    ngp_warp.render_rays  # imports the render op's modules
    assert callable(ngp_warp.composite) and ngp_warp.composite.__name__ == "composite"
