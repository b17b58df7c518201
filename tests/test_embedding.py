"""The render op as a researcher embeds it: gradients to every input they may ask for (rays_d
through a view-dependent field included), a second derivative refused in float32 and right in
float64, rays of any strides and leading shape, and a batch that misses everything still in the
graph. Each case against a pure-torch float64 pipeline on the same samples."""

import pytest
import torch

from ngp_warp import HashGridEncoding, MarchOptions, OccupancyGrid, composite, ray_marching, render_rays
from ngp_warp._reference import composite as composite_ref

AABB = torch.tensor([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0])
CENTRE = torch.tensor([0.1, -0.05, 0.0])
MARCH = MarchOptions(step_size=0.02)


def full_grid() -> OccupancyGrid:
    grid = OccupancyGrid(AABB, resolution=8)
    grid.update(0, lambda p: torch.ones(p.shape[0]))
    return grid


def rays(n: int, seed: int = 0, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays from radius 3 aimed near the centre, all through the box."""
    g = torch.Generator().manual_seed(seed)
    o = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1) * 3.0
    d = torch.nn.functional.normalize(CENTRE + (torch.rand(n, 3, generator=g) - 0.5) * 0.8 - o, dim=-1)
    return o.to(dtype), d.to(dtype)


def packed(seed: int, n_rays: int, s: int, first_ray: int = 0):
    """Random packed samples: (sigmas [S], rgbs [S, 3], t_starts, t_ends, sorted ray_indices in
    [first_ray, n_rays))."""
    g = torch.Generator().manual_seed(seed)
    ray_indices = torch.sort(torch.randint(first_ray, n_rays, (s,), generator=g)).values
    t0 = torch.rand(s, generator=g)
    t1 = t0 + 0.3 * torch.rand(s, generator=g)
    return 3 * torch.rand(s, generator=g), torch.rand(s, 3, generator=g), t0, t1, ray_indices


class ViewField(torch.nn.Module):
    """A smooth blob whose colour depends on the view direction (as a NeRF's does)."""

    def __init__(self):
        super().__init__()
        self.shine = torch.nn.Parameter(torch.tensor([1.5, -0.7, 0.9]))
        self.density = torch.nn.Parameter(torch.tensor(5.0))

    def forward(self, positions, directions):
        sigma = self.density * torch.exp(-((positions - CENTRE.to(positions)) ** 2).sum(-1) / 0.3)
        return sigma, torch.sigmoid(positions + directions * self.shine)


def reference_render(field, rays_o, rays_d, out, background=0.5):
    """float64 torch pipeline on ``out``'s samples (distances fixed): positions o + t d,
    directions d, the float64 compositing twin."""
    ri, t = out["ray_indices"], 0.5 * (out["t_starts"] + out["t_ends"]).double()
    sigmas, rgbs = field(rays_o[ri] + t[:, None] * rays_d[ri], rays_d[ri])
    rgb, opacity, _, _ = composite_ref.composite(sigmas, rgbs, out["t_starts"], out["t_ends"], ri, rays_o.shape[0], 1e-4)
    return rgb + background * (1 - opacity[:, None])


def test_rays_d_gets_the_view_dependent_fields_gradient():
    field, (rays_o, rays_d) = ViewField(), rays(48)
    d = rays_d.clone().requires_grad_(True)
    out = render_rays(rays_o, d, full_grid(), field, MARCH, background=0.5, return_samples=True)
    weights = torch.tensor([1.0, -0.5, 0.3])
    (out["rgb"] * weights).sum().backward()
    d64 = rays_d.double().requires_grad_(True)
    (reference_render(field.double(), rays_o.double(), d64, out) * weights.double()).sum().backward()
    torch.testing.assert_close(d.grad, d64.grad.float(), rtol=2e-3, atol=2e-5)
    assert d.grad.abs().max() > 1e-2
    # the part through the directions alone: the field without its view dependence differs
    field.shine.data.zero_()
    d.grad = None
    (render_rays(rays_o, d, full_grid(), field.float(), MARCH, background=0.5)["rgb"] * weights).sum().backward()
    assert (d.grad - d64.grad.float()).abs().max() > 1e-2


def test_a_second_derivative_is_refused_in_float32_and_right_in_float64():
    field, (rays_o, rays_d) = ViewField(), rays(8)
    o = rays_o.clone().requires_grad_(True)
    out = render_rays(o, rays_d, full_grid(), field, MARCH, background=0.5)
    (g,) = torch.autograd.grad(out["rgb"].sum(), o, create_graph=True)
    with pytest.raises(RuntimeError, match="differentiable once"):
        torch.autograd.grad(g.square().sum(), list(field.parameters()))
    # float64: double backward through the twin, against a pure-torch pipeline on the same samples
    field64, o64 = ViewField().double(), rays_o.double().requires_grad_(True)
    out = render_rays(o64, rays_d.double(), full_grid(), field64, MARCH, background=0.5, return_samples=True)
    (g,) = torch.autograd.grad(out["rgb"].sum(), o64, create_graph=True)
    ours = torch.autograd.grad(g.square().sum(), list(field64.parameters()))
    o_ref = rays_o.double().requires_grad_(True)
    (g,) = torch.autograd.grad(reference_render(field64, o_ref, rays_d.double(), out).sum(), o_ref, create_graph=True)
    theirs = torch.autograd.grad(g.square().sum(), list(field64.parameters()))
    for a, b in zip(ours, theirs, strict=True):
        torch.testing.assert_close(a, b)
        assert a.abs().max() > 1e-3


def test_float64_rays_pass_gradcheck_in_the_fields_parameters():
    """gradcheck in the field's parameters (the samples do not move with them; in the rays they
    do, and the op's gradient holds the distances fixed, as nerfacc's)."""
    grid, (rays_o, rays_d) = full_grid(), rays(4, dtype=torch.float64)

    def render(shine, density, background):
        def field(p, v):
            return density * torch.exp(-((p - CENTRE.double()) ** 2).sum(-1) / 0.3), torch.sigmoid(p + v * shine)

        return render_rays(rays_o, rays_d, grid, field, MARCH, background=background)["rgb"]

    inputs = (torch.tensor([1.5, -0.7, 0.9], dtype=torch.float64, requires_grad=True),
              torch.tensor(5.0, dtype=torch.float64, requires_grad=True),
              torch.tensor([0.3, 0.6, 0.9], dtype=torch.float64, requires_grad=True))  # kept in float64
    assert torch.autograd.gradcheck(render, inputs) and torch.autograd.gradgradcheck(render, inputs)


def test_composite_refuses_a_second_derivative_and_its_float64_twin_takes_one():
    n_rays = 3
    sigmas, rgbs, t0, t1, ray_indices = packed(1, n_rays, 12)
    a, b = sigmas.clone().requires_grad_(True), rgbs.clone().requires_grad_(True)
    (ga,) = torch.autograd.grad(composite(a, b, t0, t1, ray_indices, n_rays)[0].sum(), a, create_graph=True)
    with pytest.raises(RuntimeError, match="differentiable once"):
        torch.autograd.grad(ga.square().sum(), b)
    t = t0.clone().requires_grad_(True)  # the intervals too
    (gt,) = torch.autograd.grad(composite(a, b, t, t1, ray_indices, n_rays)[2].sum(), t, create_graph=True)
    with pytest.raises(RuntimeError, match="differentiable once"):
        torch.autograd.grad(gt.square().sum(), t)
    inputs = (sigmas.double().requires_grad_(True), rgbs.double().requires_grad_(True),
              t0.double().requires_grad_(True), t1.double().requires_grad_(True))
    fn = lambda x, c, s, e: composite(x, c, s, e, ray_indices, n_rays)  # noqa: E731
    assert torch.autograd.gradcheck(fn, inputs) and torch.autograd.gradgradcheck(fn, inputs)
    with pytest.raises(ValueError, match="float32 .or float64 throughout"):
        composite(inputs[0], rgbs, t0, t1, ray_indices, n_rays)


def test_rays_of_any_strides_and_leading_shape():
    field, grid = ViewField(), full_grid()
    rays_o, rays_d = rays(24)
    flat = render_rays(rays_o, rays_d, grid, field, MARCH, background=0.5)
    rotation = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(2))).Q
    transposed = (rotation @ (rays_d @ rotation).T).T  # the usual pose pattern: not contiguous
    assert not transposed.is_contiguous()
    out = render_rays(rays_o, transposed, grid, field, MARCH, background=0.5)
    torch.testing.assert_close(out["rgb"], flat["rgb"], rtol=1e-4, atol=1e-5)
    image = render_rays(rays_o.reshape(4, 6, 3), rays_d.reshape(4, 6, 3), grid, field, MARCH, background=0.5)
    assert image["rgb"].shape == (4, 6, 3) and image["opacity"].shape == image["depth"].shape == (4, 6)
    torch.testing.assert_close(image["rgb"].reshape(24, 3), flat["rgb"])
    with pytest.raises(ValueError, match="rays_o has shape"):
        render_rays(rays_o.reshape(4, 6, 3), rays_d, grid, field, MARCH)


def test_hash_grid_takes_batches_float64_and_names_a_bad_dtype():
    enc = HashGridEncoding(n_levels=4, log2_hashmap_size=8, base_resolution=4)
    with torch.no_grad():
        enc.params.uniform_(-1, 1)
    x = torch.rand(5, 7, 3)
    out = enc(x)
    assert out.shape == (5, 7, 8)
    torch.testing.assert_close(out.reshape(35, 8), enc(x.reshape(35, 3)))
    torch.testing.assert_close(enc(x.transpose(0, 1)), out.transpose(0, 1))
    enc.double()  # the float64 twin, exact in x, so gradcheck holds
    x64 = x[0].double().requires_grad_(True)
    torch.testing.assert_close(enc(x64), out[0].double(), atol=1e-6, rtol=0)
    assert torch.autograd.gradcheck(enc, (x64,)) and torch.autograd.gradgradcheck(enc, (x64,))
    with pytest.raises(ValueError, match="expects torch.float64 positions"):
        enc(x)
    enc.bfloat16()
    with pytest.raises(ValueError, match=r"params are torch.bfloat16.*\.float\(\)"):
        enc(x)
    enc.float()
    p = x.reshape(35, 3).requires_grad_(True)
    (g,) = torch.autograd.grad(enc(p).square().sum(), p, create_graph=True)
    with pytest.raises(RuntimeError, match="differentiable once"):
        torch.autograd.grad(g.sum(), enc.params)


def test_composite_is_a_torch_library_op_that_compiles_without_graph_breaks():
    from ngp_warp.ops.composite import _composite_op, _ray_offsets_op

    n_rays, s = 5, 40
    sigmas, rgbs, t0, t1, ray_indices = packed(3, n_rays, s)
    sigmas, rgbs, t0 = sigmas.requires_grad_(True), rgbs.requires_grad_(True), t0.requires_grad_(True)

    def loss(sigmas, rgbs, t0):
        rgb, opacity, depth = composite(sigmas, rgbs, t0, t1, ray_indices, n_rays)
        return rgb.square().sum() + opacity.sum() + 0.3 * depth.sum()

    torch._dynamo.reset()
    compiled = torch.compile(loss, fullgraph=True)  # a graph break would raise; inductor writes the backward
    value = compiled(sigmas, rgbs, t0)
    grads = torch.autograd.grad(value, (sigmas, rgbs, t0))
    eager = loss(sigmas, rgbs, t0)
    torch.testing.assert_close(value, eager)
    for a, b in zip(grads, torch.autograd.grad(eager, (sigmas, rgbs, t0)), strict=True):
        torch.testing.assert_close(a, b)
    assert grads[2].abs().max() > 0.1  # the intervals' gradient, through the compiled op too
    (no_interval,) = torch.autograd.grad(compiled(sigmas, rgbs, t0.detach()), sigmas)  # intervals without grad
    torch.testing.assert_close(no_interval, grads[0])
    offsets = _ray_offsets_op(ray_indices, n_rays)
    checks = torch.library.opcheck(_composite_op, (sigmas, rgbs, t0, t1, offsets, 1e-4))
    assert set(checks.values()) == {"SUCCESS"}
    with torch.device("meta"):  # shapes alone, through the fake kernels
        meta = composite(torch.empty(s), torch.empty(s, 3), torch.empty(s), torch.empty(s),
                         torch.zeros(s, dtype=torch.int64), n_rays, return_weights=True)
    assert [tuple(t.shape) for t in meta] == [(n_rays, 3), (n_rays,), (n_rays,), (s,)]


def test_the_check_script_holds_on_every_case():
    from benchmark_scripts import load_benchmark

    results = load_benchmark("check_embedding").run("cpu")
    assert len(results) == 7 and all(ok for _, ok, _ in results), results


def test_nerfacc_options_alpha_thre_per_ray_interval_and_normalised_depth():
    field, grid = ViewField(), full_grid()
    rays_o, rays_d = rays(32)
    sigma_fn = lambda x: field(x, x)[0]  # noqa: E731
    plain = render_rays(rays_o, rays_d, grid, field, MARCH, sigma_fn=sigma_fn, return_samples=True)
    thresholded = render_rays(rays_o, rays_d, grid, field, MARCH, sigma_fn=sigma_fn, alpha_thre=0.05,
                              return_samples=True)
    dt = thresholded["t_ends"] - thresholded["t_starts"]
    assert thresholded["n_samples"] < plain["n_samples"]
    kept_alpha = -torch.expm1(-field(rays_o[thresholded["ray_indices"]] + rays_d[thresholded["ray_indices"]]
                                     * (thresholded["t_starts"] + thresholded["t_ends"])[:, None] / 2,
                                     rays_d[thresholded["ray_indices"]])[0] * dt)
    assert kept_alpha.min() >= 0.05 - 1e-4
    t_min, t_max = torch.full((32,), 2.6), torch.full((32,), 3.2)
    cut = render_rays(rays_o, rays_d, grid, field, MARCH, t_min=t_min, t_max=t_max, return_samples=True)
    mid = (cut["t_starts"] + cut["t_ends"]) / 2
    assert cut["n_samples"] > 0 and mid.min() >= 2.6 and mid.max() <= 3.2
    normalised = render_rays(rays_o, rays_d, grid, field, MARCH, normalize_depth=True)
    torch.testing.assert_close(normalised["depth"], plain["depth"] / plain["opacity"], rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="alpha_thre needs a sigma_fn"):
        render_rays(rays_o, rays_d, grid, field, MARCH, alpha_thre=0.1)
    with pytest.raises(ValueError, match="t_min must be a float tensor of shape"):
        render_rays(rays_o, rays_d, grid, field, MARCH, t_min=torch.zeros(3))


def test_nerfacc_helpers_match_the_composite():
    from ngp_warp.ops.volume_rendering import accumulate_along_rays, alphas_and_transmittance, rendering

    n_rays = 6
    sigmas, rgbs, t0, t1, ray_indices = packed(4, n_rays, 50, first_ray=1)  # ray 0 has none
    sigmas.requires_grad_(True)
    rgb, opacity, depth, weights = composite(sigmas, rgbs, t0, t1, ray_indices, n_rays, return_weights=True)
    alphas, trans = alphas_and_transmittance(sigmas, t0, t1, ray_indices, n_rays)
    torch.testing.assert_close(trans * alphas, weights, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(accumulate_along_rays(weights, rgbs, ray_indices, n_rays), rgb, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(accumulate_along_rays(weights, None, ray_indices, n_rays)[:, 0], opacity)
    (g_ours,) = torch.autograd.grad((trans * alphas).square().sum(), sigmas)
    (g_kernel,) = torch.autograd.grad(weights.square().sum(), sigmas)
    torch.testing.assert_close(g_ours, g_kernel, rtol=1e-4, atol=1e-6)
    seen = {}

    def rgb_sigma_fn(t_starts, t_ends, rays):
        seen.update(t_starts=t_starts, rays=rays)
        return rgbs, sigmas

    colours, opacities, depths, extras = rendering(t0, t1, ray_indices, n_rays, rgb_sigma_fn,
                                                   render_bkgd=torch.ones(3))
    assert seen["t_starts"] is t0 and seen["rays"] is ray_indices
    torch.testing.assert_close(colours, rgb + (1 - opacity[:, None]))
    assert opacities.shape == depths.shape == (n_rays, 1) and set(extras) == {"weights", "alphas", "trans"}


def test_the_encoding_compiles_without_graph_breaks():
    import copy

    from ngp_warp.ops.hashgrid_autograd import _encode_op

    enc = HashGridEncoding(n_levels=4, log2_hashmap_size=8, base_resolution=4)
    with torch.no_grad():
        enc.params.uniform_(-1, 1)
    enc = copy.deepcopy(enc)  # a copy is known to the op too
    x = torch.rand(50, 3, requires_grad=True)

    def loss(x):
        return enc(x).square().sum()

    torch._dynamo.reset()
    value = torch.compile(loss, fullgraph=True, backend="aot_eager")(x)
    grads = torch.autograd.grad(value, (x, enc.params))
    eager = loss(x)
    torch.testing.assert_close(value, eager)
    for a, b in zip(grads, torch.autograd.grad(eager, (x, enc.params)), strict=True):
        torch.testing.assert_close(a, b)
    checks = torch.library.opcheck(_encode_op, (x, enc.params, id(enc)))
    assert set(checks.values()) == {"SUCCESS"}


def test_march_and_composite_compile_into_one_graph():
    import copy

    grid = copy.deepcopy(full_grid())  # a copy is known to the op too
    rays_o, rays_d = rays(16)
    density = torch.tensor(3.0, requires_grad=True)

    def loss(o, d):
        s = ray_marching(o, d, grid, MARCH, validate=False)
        sigmas = density * torch.exp(-s.positions.square().sum(-1))
        rgb, _, _ = composite(sigmas, torch.sigmoid(s.positions), s.t_starts, s.t_ends, s.ray_indices, 16,
                              validate=False)
        return rgb.sum()

    torch._dynamo.reset()
    compiled = torch.compile(loss, fullgraph=True, backend="aot_eager")
    for d in (rays_d, -rays_d):  # the second batch misses the box: no sample at all
        value = compiled(rays_o, d)
        torch.testing.assert_close(value, loss(rays_o, d))
    value = compiled(rays_o, rays_d)
    (grad,) = torch.autograd.grad(value, density)
    torch.testing.assert_close(grad, torch.autograd.grad(loss(rays_o, rays_d), density)[0])
    assert value > 0 and grad > 0


def test_torch_func_grad_and_vmap_take_the_composite_and_jacrev_is_refused_in_one_line():
    n_rays, s = 3, 12
    sigmas, rgbs, t0, t1, ray_indices = packed(5, n_rays, s)

    def opacity(x):
        return composite(x, rgbs, t0, t1, ray_indices, n_rays, validate=False)[1]

    x = sigmas.clone().requires_grad_(True)
    torch.testing.assert_close(torch.func.grad(lambda x: opacity(x).square().sum())(sigmas),
                               torch.autograd.grad(opacity(x).square().sum(), x)[0])
    batch = torch.rand(4, s, generator=torch.Generator().manual_seed(6))
    stacked = torch.vmap(opacity)(batch)
    assert stacked.shape == (4, n_rays)
    for k in range(4):
        torch.testing.assert_close(stacked[k], opacity(batch[k]))
    with pytest.raises(ValueError, match="cannot be vmapped"):
        torch.func.jacrev(opacity)(sigmas)
    jacobian = torch.func.jacrev(lambda x: composite_ref.composite(x, rgbs.double(), t0.double(), t1.double(),
                                                                   ray_indices, n_rays)[1])(sigmas.double())
    assert jacobian.shape == (n_rays, s)  # the float64 twin takes every transform


def test_torch_func_grad_and_vmap_take_the_encoding_and_jacrev_is_refused_in_one_line():
    torch.manual_seed(7)
    enc = HashGridEncoding(n_levels=4, log2_hashmap_size=10)
    with torch.no_grad():
        enc.params.uniform_(-1, 1)  # never all zero: every gradient below is non-trivial
    x = torch.rand(64, 3)

    def loss(params, points):
        return torch.func.functional_call(enc, {"params": params}, (points,)).square().sum()

    points = x.clone().requires_grad_(True)
    want_params, want_x = torch.autograd.grad(loss(enc.params, points), (enc.params, points))
    got_params, got_x = torch.func.grad(loss, argnums=(0, 1))(enc.params.detach(), x)
    torch.testing.assert_close(got_params, want_params)
    torch.testing.assert_close(got_x, want_x)
    assert want_x.abs().sum() > 0 and want_params.abs().sum() > 0
    grid = x.view(8, 8, 3)  # vmap over points: one longer list; over tables: one table at a time
    torch.testing.assert_close(torch.vmap(enc, in_dims=1)(grid), enc(grid.transpose(0, 1).reshape(64, 3)).view(8, 8, -1))
    tables = torch.stack([enc.params.detach(), 2 * enc.params.detach()])
    both = torch.vmap(lambda p: torch.func.functional_call(enc, {"params": p}, (x,)))(tables)
    torch.testing.assert_close(both[1], torch.func.functional_call(enc, {"params": tables[1]}, (x,)))
    with pytest.raises(ValueError, match="HashGridEncoding's Warp backward cannot be vmapped"):
        torch.func.jacrev(enc)(x[:2])
