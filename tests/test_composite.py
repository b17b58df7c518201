import pytest
import torch

from ngp_warp import composite
from ngp_warp._reference import composite as composite_ref
from ngp_warp.ops.composite import ray_offsets_from_indices


def packed_rays(n_rays=96, max_per_ray=48, device="cpu"):
    """Random packed samples: empty rays (first, last and every 7th), translucent rays (every 5th),
    tiny to large densities."""
    counts = torch.randint(1, max_per_ray, (n_rays,))
    counts[::7] = 0
    counts[-2:] = 0
    ray_indices = torch.repeat_interleave(torch.arange(n_rays), counts)
    s = int(counts.sum())
    deltas = torch.rand(s) * 0.05 + 0.002
    t_starts = torch.cumsum(deltas + torch.rand(s) * 0.02, 0) + 0.5
    t_ends = t_starts + deltas
    kind = torch.rand(s)
    sigmas = torch.where(kind < 0.2, torch.rand(s) * 1e-3, torch.rand(s) * 40.0) * (kind > 0.05)
    sigmas = torch.where(ray_indices % 5 == 0, sigmas * 0.01, sigmas)
    rgbs = torch.rand(s, 3)
    return [x.to(device) for x in (sigmas, rgbs, t_starts, t_ends, ray_indices)] + [n_rays]


def assert_close64(actual, expected, rtol=1e-4, atol=1e-6):
    torch.testing.assert_close(actual.double().cpu(), expected.detach().double().cpu(), rtol=rtol, atol=atol)


def test_offsets_from_indices_match_searchsorted():
    *_, ray_indices, n_rays = packed_rays()
    assert ray_indices[0] > 0 and ray_indices[-1] < n_rays - 1  # leading and trailing empty rays
    offsets = ray_offsets_from_indices(ray_indices, n_rays)
    assert offsets.dtype == torch.int32
    assert torch.equal(offsets.long(), composite_ref.ray_offsets_from_indices(ray_indices, n_rays))


@pytest.mark.parametrize("eps", [0.0, 1e-3, 0.2])
def test_forward_matches_float64_reference(eps):
    sigmas, rgbs, t_starts, t_ends, ray_indices, n_rays = packed_rays()
    rgb, opacity, depth, weights = composite(sigmas, rgbs, t_starts, t_ends, ray_indices, n_rays, eps, return_weights=True)
    ref = composite_ref.composite(sigmas, rgbs, t_starts, t_ends, ray_indices, n_rays, eps)
    for actual, expected in zip((rgb, opacity, depth, weights), ref):
        assert_close64(actual, expected)
    assert (opacity > 0.98 - eps).sum() > 10 and ((opacity > 0) & (opacity < 0.5)).sum() > 10


@pytest.mark.parametrize("eps", [0.0, 1e-2])
def test_backward_matches_float64_autograd(eps):
    sigmas, rgbs, t_starts, t_ends, ray_indices, n_rays = packed_rays()
    sigmas.requires_grad_(True)
    rgbs.requires_grad_(True)
    outs = composite(sigmas, rgbs, t_starts, t_ends, ray_indices, n_rays, eps, return_weights=True)
    grads = [torch.randn_like(o) for o in outs]
    g_sigmas, g_rgbs = torch.autograd.grad(outs, (sigmas, rgbs), grads)

    s64 = sigmas.detach().double().requires_grad_(True)
    c64 = rgbs.detach().double().requires_grad_(True)
    ref = composite_ref.composite(s64, c64, t_starts.double(), t_ends.double(), ray_indices, n_rays, eps)
    r_sigmas, r_rgbs = torch.autograd.grad(ref, (s64, c64), [g.double() for g in grads])
    assert_close64(g_sigmas, r_sigmas)
    assert_close64(g_rgbs, r_rgbs)
    assert (g_sigmas > 0).any() and (g_sigmas < 0).any()


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
@pytest.mark.parametrize("eps", [0.0, 1e-2])
@pytest.mark.parametrize("used", [(0, 1, 2, 3), (2,), (1, 3)])
def test_interval_gradients_match_float64_autograd(eps, used, device):
    """t_starts and t_ends get the twin's gradient: through σ·δ in every output, and through the
    midpoints in depth (also when depth is the only output used)."""
    sigmas, rgbs, t_starts, t_ends, ray_indices, n_rays = packed_rays()
    t_starts.requires_grad_(True)
    t_ends.requires_grad_(True)
    outs = composite(*(x.to(device) for x in (sigmas, rgbs, t_starts, t_ends, ray_indices)), n_rays, eps,
                     return_weights=True)
    grads = [torch.randn_like(o) if k in used else torch.zeros_like(o) for k, o in enumerate(outs)]
    g_starts, g_ends = torch.autograd.grad([outs[k] for k in used], (t_starts, t_ends), [grads[k] for k in used])
    grads = [g.cpu() for g in grads]

    ts64 = t_starts.detach().double().requires_grad_(True)
    te64 = t_ends.detach().double().requires_grad_(True)
    ref = composite_ref.composite(sigmas.double(), rgbs.double(), ts64, te64, ray_indices, n_rays, eps)
    r_starts, r_ends = torch.autograd.grad([ref[k] for k in used], (ts64, te64), [grads[k].double() for k in used])
    assert r_ends.abs().max() > 1.0
    # σ (up to 40 here) times G, a difference of float32 sums: CUDA's rounding reached 1.8e-4
    assert_close64(g_starts, r_starts, rtol=1e-3, atol=1e-3)
    assert_close64(g_ends, r_ends, rtol=1e-3, atol=1e-3)


@pytest.mark.parametrize("used", [(0,), (1, 2), (3,), (0, 3)])
def test_backward_with_some_outputs_unused(used):
    """Outputs that get no gradient count as zero (the kernel skips them)."""
    sigmas, rgbs, t_starts, t_ends, ray_indices, n_rays = packed_rays()
    sigmas.requires_grad_(True)
    rgbs.requires_grad_(True)
    outs = composite(sigmas, rgbs, t_starts, t_ends, ray_indices, n_rays, 1e-3, return_weights=True)
    grads = [torch.randn_like(o) for o in outs]
    g_sigmas, g_rgbs = torch.autograd.grad([outs[k] for k in used], (sigmas, rgbs), [grads[k] for k in used],
                                           allow_unused=True)
    s64 = sigmas.detach().double().requires_grad_(True)
    c64 = rgbs.detach().double().requires_grad_(True)
    ref = composite_ref.composite(s64, c64, t_starts.double(), t_ends.double(), ray_indices, n_rays, 1e-3)
    r_sigmas, r_rgbs = torch.autograd.grad([ref[k] for k in used], (s64, c64), [grads[k].double() for k in used],
                                           allow_unused=True)
    assert_close64(g_sigmas, r_sigmas)
    if r_rgbs is None:
        assert g_rgbs is None or not g_rgbs.any()
    else:
        assert_close64(g_rgbs, r_rgbs)
    assert g_sigmas.abs().max() > 1e-3


def test_backward_twin_matches_autograd_in_float64():
    sigmas, rgbs, t_starts, t_ends, ray_indices, n_rays = packed_rays()
    s64 = sigmas.double().requires_grad_(True)
    c64 = rgbs.double().requires_grad_(True)
    t0, t1 = t_starts.double().requires_grad_(True), t_ends.double().requires_grad_(True)
    ref = composite_ref.composite(s64, c64, t0, t1, ray_indices, n_rays, 1e-3)
    grads = [torch.randn_like(o) for o in ref]
    expected = torch.autograd.grad(ref, (s64, c64, t0, t1), grads)
    twin = composite_ref.composite_backward(s64.detach(), c64.detach(), t0.detach(), t1.detach(), ray_indices,
                                            n_rays, *grads, 1e-3)
    for got, want in zip(twin, expected, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)


def test_early_stop_zeroes_later_samples_and_their_gradients():
    sigmas, rgbs, t_starts, t_ends, ray_indices, n_rays = packed_rays()
    sigmas.requires_grad_(True)
    rgbs.requires_grad_(True)
    eps = 0.05
    rgb, opacity, depth, weights = composite(sigmas, rgbs, t_starts, t_ends, ray_indices, n_rays, eps, return_weights=True)
    (rgb.sum() + depth.sum()).backward()
    delta = (t_ends - t_starts).double()
    tau = torch.zeros(sigmas.shape[0], dtype=torch.float64)
    offsets = composite_ref.ray_offsets_from_indices(ray_indices, n_rays)
    for r in range(n_rays):
        s = slice(offsets[r], offsets[r + 1])
        x = sigmas.detach()[s].double() * delta[s]
        tau[s] = torch.cumsum(x, 0) - x
    stopped = torch.exp(-tau) < eps * 0.99
    assert stopped.sum() > 50
    assert (weights[stopped] == 0).all() and (sigmas.grad[stopped] == 0).all() and (rgbs.grad[stopped] == 0).all()
    alive = torch.exp(-tau) > eps * 1.01
    assert (weights[alive & (sigmas > 0.1)] > 0).all()


@pytest.mark.filterwarnings("ignore:Input #")
def test_gradcheck():
    sigmas, rgbs, t_starts, t_ends, ray_indices, n_rays = packed_rays(n_rays=6, max_per_ray=6)
    sigmas = (sigmas.clamp(min=0.5) * 0.2).requires_grad_(True)
    rgbs.requires_grad_(True)

    def fn(s, c):
        rgb, opacity, depth, weights = composite(s, c, t_starts, t_ends, ray_indices, n_rays, return_weights=True)
        return rgb, opacity, depth * 0.1, weights

    assert torch.autograd.gradcheck(fn, (sigmas, rgbs), eps=1e-3, atol=2e-3, rtol=1e-2, fast_mode=False)


def test_int32_indices_and_no_samples():
    sigmas, rgbs, t_starts, t_ends, ray_indices, n_rays = packed_rays()
    a = composite(sigmas, rgbs, t_starts, t_ends, ray_indices, n_rays)
    b = composite(sigmas, rgbs, t_starts, t_ends, ray_indices.int(), n_rays)
    for x, y in zip(a, b):
        assert torch.equal(x, y)
    empty = torch.zeros(0)
    rgb, opacity, depth, weights = composite(empty, torch.zeros(0, 3), empty, empty, torch.zeros(0, dtype=torch.long), 5,
                                             return_weights=True)
    assert rgb.shape == (5, 3) and opacity.shape == (5,) and depth.shape == (5,) and weights.shape == (0,)
    assert not rgb.any() and not opacity.any()


def _bad_inputs():
    sigmas, rgbs, t_starts, t_ends, ray_indices, n_rays = packed_rays(n_rays=8, max_per_ray=5)
    ok = dict(sigmas=sigmas, rgbs=rgbs, t_starts=t_starts, t_ends=t_ends, ray_indices=ray_indices, n_rays=n_rays)
    yield "rank", {**ok, "sigmas": sigmas[:, None]}
    yield "rgb shape", {**ok, "rgbs": rgbs[:, :2]}
    yield "length", {**ok, "t_ends": t_ends[:-1]}
    yield "dtype", {**ok, "rgbs": rgbs.double()}
    yield "index dtype", {**ok, "ray_indices": ray_indices.float()}
    yield "n_rays", {**ok, "n_rays": 0}
    yield "eps", {**ok, "early_stop_eps": -1.0}


@pytest.mark.parametrize("case", list(_bad_inputs()), ids=lambda c: c[0])
def test_invalid_inputs_raise_value_error(case):
    with pytest.raises(ValueError):
        composite(**case[1])


@pytest.mark.cuda
def test_cuda_matches_cpu():
    sigmas, rgbs, t_starts, t_ends, ray_indices, n_rays = packed_rays()
    outs, grads = [], []
    for device in ("cpu", "cuda"):
        s = sigmas.detach().to(device).requires_grad_(True)
        c = rgbs.detach().to(device).requires_grad_(True)
        out = composite(s, c, t_starts.to(device), t_ends.to(device), ray_indices.to(device), n_rays, 1e-3,
                        return_weights=True)
        (out[0].sum() + out[1].sum() * 0.5 + out[2].sum() * 0.1 + out[3].sum()).backward()
        outs.append([o.detach().cpu() for o in out])
        grads.append([s.grad.cpu(), c.grad.cpu()])
    for a, b in zip(outs[0] + grads[0], outs[1] + grads[1]):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
