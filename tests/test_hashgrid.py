"""HashGridEncoding: level table, values and both gradients against the float64 reference."""

import copy
import io
import math

import pytest
import torch

from ngp_warp import HashGridEncoding
from ngp_warp._reference.hashgrid import encode_like
from ngp_warp.ops.hashgrid import level_table


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    return ((a.double() - b.double()).norm() / b.double().norm().clamp_min(1e-300)).item()


def run_both(enc: HashGridEncoding, x: torch.Tensor, grad_out: torch.Tensor | None = None):
    """Encoding output, d/dparams and d/dx of the Warp op and of the float64 reference."""
    x = x.detach().clone().requires_grad_()
    enc.zero_grad(set_to_none=True)
    y = enc(x)
    if grad_out is None:
        grad_out = torch.randn_like(y)
    y.backward(grad_out)
    x64 = x.detach().double().requires_grad_()
    p64 = enc.params.detach().double().requires_grad_()
    y64 = encode_like(enc, x64, p64)
    y64.backward(grad_out.double())
    return (y, enc.params.grad, x.grad), (y64, p64.grad, x64.grad)


# (D, L, F, log2T, base, per-level scale, interpolation, N, x range): every F, both D, both
# interpolations; small tables so that every config has dense and hashed levels
CONFIGS = [
    (3, 6, 2, 10, 4, 1.8, "linear", 1000, (0.0, 1.0)),
    (3, 5, 1, 9, 3, 2.0, "smoothstep", 700, (0.0, 1.0)),
    (3, 4, 4, 8, 5, 1.6, "linear", 500, (0.0, 1.0)),
    (3, 3, 8, 7, 2, 2.5, "smoothstep", 400, (0.0, 1.0)),
    (2, 6, 1, 8, 4, 1.9, "linear", 800, (0.0, 1.0)),
    (2, 5, 2, 7, 6, 1.5, "smoothstep", 600, (0.0, 1.0)),
    (2, 4, 4, 9, 3, 2.7, "smoothstep", 500, (0.0, 1.0)),
    (2, 3, 8, 6, 2, 3.0, "linear", 300, (0.0, 1.0)),
    # tcnn semantics outside [0, 1]: no clamp, uint32 wrap of negative cells
    (3, 4, 2, 8, 4, 2.0, "linear", 800, (-0.6, 1.7)),
    (2, 4, 4, 6, 3, 2.0, "smoothstep", 600, (-1.0, 2.0)),
    # several CPU threads, each on whole levels (the table gradient has no atomics there)
    (3, 4, 2, 12, 8, 2.0, "linear", 6000, (0.0, 1.0)),
]


@pytest.mark.parametrize("cfg", CONFIGS, ids=lambda c: f"D{c[0]}L{c[1]}F{c[2]}T{c[3]}{c[6][0]}N{c[7]}")
def test_matches_float64_reference(cfg):
    D, L, F, T, base, scale, interp, n, (lo, hi) = cfg
    enc = HashGridEncoding(D, L, F, T, base, scale, interp)
    assert any(enc.hashed) and not all(enc.hashed), "config must mix dense and hashed levels"
    with torch.no_grad():
        enc.params.uniform_(-1.0, 1.0)
    x = torch.rand(n, D) * (hi - lo) + lo
    (y, gp, gx), (y64, gp64, gx64) = run_both(enc, x)
    assert y.shape == (n, L * F) and y.dtype == torch.float32
    assert rel_err(y, y64) < 2e-6
    assert rel_err(gp, gp64) < 2e-6
    assert rel_err(gx, gx64) < 1e-5
    # level-major layout: level l's features are columns l*F ... l*F + F - 1
    one = HashGridEncoding(D, 1, F, T, base, scale, interp)
    with torch.no_grad():
        one.params.copy_(enc.params[: one.n_params])
        assert torch.allclose(one(x.contiguous()), y[:, :F], rtol=0, atol=0)


@pytest.mark.parametrize("lanes,levels,paired", [(4, 1, True), (3, 2, True), (2, 3, False), (8, 1, True)])
@pytest.mark.parametrize("cfg", [CONFIGS[0], CONFIGS[4], CONFIGS[8]], ids=lambda c: f"D{c[0]}F{c[2]}")
def test_cuda_schedules_on_cpu(cfg, lanes, levels, paired):
    """The GPU's scheduling variants (lanes per point, levels per item, x-pairs) on the CPU."""
    D, L, F, T, base, scale, interp, n, (lo, hi) = cfg
    enc = HashGridEncoding(D, L, F, T, base, scale, interp)
    enc._cuda_schedule_on_cpu = True
    enc.cuda_level_lanes, enc.cuda_levels_per_thread, enc.cuda_paired = lanes, levels, paired
    with torch.no_grad():
        enc.params.uniform_(-1.0, 1.0)
    x = torch.rand(n, D) * (hi - lo) + lo
    (y, gp, gx), (y64, gp64, gx64) = run_both(enc, x)
    assert rel_err(y, y64) < 2e-6 and rel_err(gp, gp64) < 2e-6 and rel_err(gx, gx64) < 1e-5


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
@pytest.mark.parametrize("cuda_schedule", [False, True])
@pytest.mark.parametrize("cfg", [CONFIGS[1], CONFIGS[0], CONFIGS[2], CONFIGS[3]], ids=lambda c: f"F{c[2]}")
def test_bfloat16_encoding_is_the_rounded_float32_encoding(cfg, cuda_schedule, device):
    D, L, F, T, base, scale, interp, n, (lo, hi) = cfg
    enc = HashGridEncoding(D, L, F, T, base, scale, interp).to(device)
    enc._cuda_schedule_on_cpu = cuda_schedule
    with torch.no_grad():
        enc.params.uniform_(-1.0, 1.0)
    x = (torch.rand(n, D) * (hi - lo) + lo).to(device)
    full = enc.encode(x)
    half = enc.encode(x, torch.bfloat16)
    assert half.dtype == torch.bfloat16 and half.shape == (n, L * F) and not half.requires_grad
    assert full.abs().min() > 0 and torch.equal(full, enc(x).detach())
    assert torch.equal(half.view(torch.int16), full.to(torch.bfloat16).view(torch.int16))


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
def test_bfloat16_encoding_rounds_ties_to_even(device):
    # One dense level at scale 2: points with coordinates 0.25 or 0.75 sit on grid vertices,
    # so the output is a table entry exactly; the entries are halfway between bfloat16s.
    enc = HashGridEncoding(3, 1, 2, 8, 3, 2.0).to(device)
    assert enc.scales == (2.0,) and not enc.hashed[0]
    ulp = 2.0**-7  # bfloat16 spacing in [1, 2)
    ties = torch.tensor([1 + ulp / 2, 1 + 3 * ulp / 2, -(1 + ulp / 2), -(1 + 5 * ulp / 2), 2 ** -130 * 3, 65504.0])
    with torch.no_grad():
        enc.params.copy_(ties.repeat(enc.n_params // ties.numel() + 1)[: enc.n_params])
    x = torch.tensor([[a, b, c] for a in (0.25, 0.75) for b in (0.25, 0.75) for c in (0.25, 0.75)], device=device)
    full = enc.encode(x)
    assert set(full.flatten().tolist()) <= set(ties.tolist()) and len(set(full.flatten().tolist())) > 3
    assert torch.equal(enc.encode(x, torch.bfloat16).view(torch.int16), full.to(torch.bfloat16).view(torch.int16))
    with pytest.raises(ValueError, match="dtype"):
        enc.encode(x, torch.float16)


def test_default_level_table_matches_tcnn():
    """The NeRF configuration: 3 dense levels (16^3, 32^3, 64^3), then 13 of 2^19 entries.

    Levels 12 to 15 (resolutions 2^16 ... 2^19) are *not* hashed in tcnn: its index loop's
    uint32 stride wraps to 0 after res^2 = 2^32 ..., so it ends below the table size and tcnn
    indexes those levels as ``(x + y*res) mod 2^19`` (z times a stride of 0). Mirrored here.
    """
    enc = HashGridEncoding()
    assert enc.n_output_dims == 32
    assert enc.resolutions == tuple(16 * 2**l for l in range(16))
    assert enc.scales == tuple(16.0 * 2**l - 1.0 for l in range(16))
    assert enc.sizes == (4096, 32768, 262144) + (2**19,) * 13
    assert enc.hashed == (False,) * 3 + (True,) * 9 + (False,) * 4
    # a finest resolution of 2048 (instant-NGP's NeRF grid) stays clear of the wrap
    ngp = HashGridEncoding.from_finest_resolution(2048)
    assert ngp.hashed == (False,) * 5 + (True,) * 11
    assert enc.offsets[:4] == (0, 4096, 36864, 299008)
    assert enc.n_params == 2 * (299008 + 13 * 2**19) == 14229504
    assert enc.params.shape == (enc.n_params,) and enc.params.dtype == torch.float32
    assert enc.params.abs().max() <= 1e-4 and enc.params.std() > 1e-5


def test_level_table_rounding_and_alignment():
    # non-integer scales: float32 exp2 / log2 as tcnn, resolution = ceil(scale) + 1
    t = level_table(3, 4, 14, 16, 1.5)
    assert t.scales[1] == pytest.approx(23.0) and t.resolutions[1] == 24
    assert t.scales[2] == pytest.approx(35.0, rel=1e-6) and t.resolutions[2] == 36
    # 2-D: 10^2 = 100 entries rounded up to a multiple of 8
    t = level_table(2, 2, 10, 10, 1.0)
    assert t.scales == (9.0, 9.0) and t.resolutions == (10, 10)
    assert t.sizes == (104, 104) and t.offsets == (0, 104, 208) and t.hashed == (False, False)
    # hashed as soon as res^D exceeds the table
    t = level_table(3, 2, 12, 16, 1.01)  # 16^3 = 4096 fits 2^12 exactly, 17^3 does not
    assert t.resolutions == (16, 17) and t.sizes == (4096, 4096) and t.hashed == (False, True)


def test_uint32_stride_wrap_like_tcnn():
    """A level whose res^2 is 2^32 is indexed densely with z ignored, exactly as tcnn does."""
    enc = HashGridEncoding(3, 1, 1, 16, 65536, 2.0)
    assert enc.resolutions == (65536,) and enc.hashed == (False,) and enc.sizes == (65536,)
    with torch.no_grad():
        enc.params.uniform_(-1.0, 1.0)
    x = torch.rand(200, 3)
    x2 = x.clone()
    x2[:, 2] = torch.rand(200)  # another z
    assert torch.allclose(enc(x), enc(x2), rtol=0, atol=1e-6)  # equal up to rounding of the z weights
    (y, gp, gx), (y64, gp64, gx64) = run_both(enc, x)
    assert rel_err(y, y64) < 2e-6 and rel_err(gp, gp64) < 2e-6 and rel_err(gx, gx64) < 1e-5
    assert gx[:, 2].abs().max() < 1e-4 * gx[:, :2].abs().max()


def test_desired_resolution():
    enc = HashGridEncoding(n_levels=16, base_resolution=16, desired_resolution=2048)
    assert enc.per_level_scale == pytest.approx(math.exp(math.log(2048 / 16) / 15))
    assert enc.resolutions[-1] in (2048, 2049)  # ceil(2048 - 1 +- float32 rounding) + 1
    other = HashGridEncoding.from_finest_resolution(2048, n_levels=16, base_resolution=16)
    assert other.per_level_scale == enc.per_level_scale and other.n_params == enc.n_params
    with pytest.raises(ValueError):
        HashGridEncoding(per_level_scale=1.5, desired_resolution=512)


@pytest.mark.filterwarnings("ignore:Input #")  # float32 on purpose: the op is float32-only
def test_gradcheck_params_and_x():
    """torch.autograd.gradcheck in float32, at points away from cell faces."""
    for interp in ("linear", "smoothstep"):
        for D in (2, 3):
            enc = HashGridEncoding(D, 2, 2, 6, 2, 2.0, interp)  # scales 1 and 3
            with torch.no_grad():
                enc.params.uniform_(-1.0, 1.0)
            x = torch.rand(4000, D)
            # distance of every coordinate to the nearest cell face, on every level
            dist = torch.stack([((s * x + 0.5) - (s * x + 0.5).round()).abs() for s in enc.scales]).amin(0)
            x = x[(dist > 0.02).all(1)][:6].clone().requires_grad_()
            params = enc.params.detach().clone().requires_grad_()
            fn = lambda x_, p_: encode_fn(enc, x_, p_)  # noqa: E731
            assert torch.autograd.gradcheck(fn, (x, params), eps=1e-3, atol=2e-3, rtol=1e-2)


def encode_fn(enc, x, params):
    from ngp_warp.ops.hashgrid_autograd import HashGridFunction

    return HashGridFunction.apply(x, params, enc)


def test_empty_batch():
    enc = HashGridEncoding(3, 4, 2, 10, 4, 2.0)
    x = torch.zeros(0, 3, requires_grad=True)
    y = enc(x)
    assert y.shape == (0, 8)
    y.sum().backward()
    assert x.grad.shape == (0, 3)
    assert enc.params.grad.shape == (enc.n_params,) and not enc.params.grad.any()


def test_gradients_only_when_needed():
    enc = HashGridEncoding(3, 4, 2, 10, 4, 2.0)
    x = torch.rand(100, 3)
    enc(x).sum().backward()  # x needs no gradient
    assert x.grad is None and enc.params.grad is not None
    enc.params.requires_grad_(False)
    xr = x.clone().requires_grad_()
    enc(xr).sum().backward()  # params need none
    assert xr.grad is not None and xr.grad.abs().sum() > 0
    with torch.no_grad():
        assert enc(x).shape == (100, 8)


def test_half_precision_gradient_close_to_float32():
    enc = HashGridEncoding(3, 6, 2, 10, 4, 1.8)
    with torch.no_grad():
        enc.params.uniform_(-1.0, 1.0)
    x = torch.rand(3000, 3)
    g = torch.randn(3000, enc.n_output_dims)
    (_, gp32, _), (_, gp64, _) = run_both(enc, x, g)
    enc.grad_dtype = torch.float16
    (_, gp16, _), _ = run_both(enc, x, g)
    hashed_from = enc.offsets[enc.hashed.index(True)] * enc.n_features_per_level
    assert torch.equal(gp16[:hashed_from], gp32[:hashed_from])  # dense levels stay float32
    err = rel_err(gp16[hashed_from:], gp64[hashed_from:])
    assert 1e-6 < err < 3e-3, err  # lossy, but only by half-precision rounding
    assert rel_err(gp32, gp64) < 2e-6


def test_bad_input_raises_value_error():
    enc = HashGridEncoding(3, 2, 2, 8, 4, 2.0)
    bad_inputs = (
        torch.rand(10),  # width 1
        torch.rand(10, 2),  # width
        torch.rand(2, 10, 2),  # width, batched
        torch.rand(10, 3).double(),  # dtype (float64 needs float64 params)
        torch.zeros(10, 3, dtype=torch.int32),
    )
    for bad in bad_inputs:
        with pytest.raises(ValueError):
            enc(bad)
    with pytest.raises(ValueError):
        enc([[0.5, 0.5, 0.5]])
    for kwargs in (
        {"n_input_dims": 4},
        {"n_features_per_level": 3},
        {"log2_hashmap_size": 31},
        {"interpolation": "cubic"},
        {"grad_dtype": torch.bfloat16},
    ):
        with pytest.raises(ValueError):
            HashGridEncoding(**kwargs)


def test_state_dict_round_trip():
    """A tcnn-style state dict holds exactly one flat float32 'params' tensor."""
    a = HashGridEncoding(3, 4, 2, 10, 4, 2.0)
    sd = a.state_dict()
    assert list(sd) == ["params"] and sd["params"].shape == (a.n_params,)
    b = HashGridEncoding(3, 4, 2, 10, 4, 2.0)
    b.load_state_dict(sd)
    x = torch.rand(50, 3)
    assert torch.equal(a(x), b(x))


def test_copy_and_pickle():
    enc = HashGridEncoding(3, 4, 2, 8, 4, 2.0)
    x = torch.rand(10, 3)
    y = enc(x)  # fills the module's cache of Warp views
    assert torch.equal(copy.deepcopy(enc)(x), y)
    buf = io.BytesIO()
    torch.save(enc, buf)
    buf.seek(0)
    assert torch.equal(torch.load(buf, weights_only=False)(x), y)


def test_non_contiguous_input():
    enc = HashGridEncoding(3, 3, 2, 8, 4, 2.0)
    x = torch.rand(3, 64).t()[:, :3]  # [64, 3] view with strides (1, 64)
    assert not x.is_contiguous()
    assert torch.equal(enc(x), enc(x.contiguous()))


# -- CUDA ---------------------------------------------------------------------------------


@pytest.mark.cuda
def test_cuda_device_mismatch_raises():
    enc = HashGridEncoding(3, 2, 2, 8, 4, 2.0)
    with pytest.raises(ValueError):
        enc(torch.rand(10, 3, device="cuda"))
    enc = enc.cuda()
    with pytest.raises(ValueError):
        enc(torch.rand(10, 3))


CUDA_VARIANTS = [
    {},
    {"cuda_level_lanes": 1, "cuda_levels_per_thread": 1, "cuda_paired": False, "cuda_dx_levels_per_thread": 0},
    {"cuda_level_lanes": 2, "cuda_levels_per_thread": 3, "cuda_paired": True, "cuda_dx_levels_per_thread": 2},
    {"cuda_level_lanes": 3, "cuda_levels_per_thread": 2, "cuda_paired": False, "cuda_dx_levels_per_thread": 5},
]


CUDA_CASES = [(cfg, 0) for cfg in CONFIGS[:10]] + [(CONFIGS[i], v) for i in (0, 6, 8) for v in (1, 2, 3)]


@pytest.mark.cuda
@pytest.mark.parametrize(
    "cfg,variant", CUDA_CASES, ids=[f"D{c[0]}L{c[1]}F{c[2]}T{c[3]}{c[6][0]}-v{v}" for c, v in CUDA_CASES]
)
def test_cuda_matches_cpu(cfg, variant):
    D, L, F, T, base, scale, interp, n, (lo, hi) = cfg
    cpu = HashGridEncoding(D, L, F, T, base, scale, interp)
    with torch.no_grad():
        cpu.params.uniform_(-1.0, 1.0)
    gpu = HashGridEncoding(D, L, F, T, base, scale, interp, device="cuda")
    for k, v in CUDA_VARIANTS[variant].items():
        setattr(gpu, k, v)
    gpu.load_state_dict(cpu.state_dict())
    x = torch.rand(n, D) * (hi - lo) + lo
    g = torch.randn(n, L * F)
    outs = []
    for enc, dev in ((cpu, "cpu"), (gpu, "cuda")):
        xd = x.to(dev).detach().requires_grad_()
        y = enc(xd)
        y.backward(g.to(dev))
        outs.append((y.cpu(), enc.params.grad.cpu(), xd.grad.cpu()))
    (y0, p0, x0), (y1, p1, x1) = outs
    assert rel_err(y1, y0) < 1e-6
    assert rel_err(p1, p0) < 1e-6  # float additions in another order
    assert rel_err(x1, x0) < 1e-5


@pytest.mark.cuda
def test_cuda_half_gradient_and_stream():
    enc = HashGridEncoding(3, 6, 2, 10, 4, 1.8, device="cuda", grad_dtype=torch.float16)
    with torch.no_grad():
        enc.params.uniform_(-1.0, 1.0)
    x = torch.rand(5000, 3, device="cuda")
    g = torch.randn(5000, enc.n_output_dims, device="cuda")
    stream = torch.cuda.Stream()
    with torch.cuda.stream(stream):  # runs on the current stream, not the default one
        (y, gp16, _), (y64, gp64, _) = run_both(enc, x, g)
    torch.cuda.synchronize()
    assert rel_err(y, y64) < 2e-6
    assert rel_err(gp16, gp64) < 3e-3


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
@pytest.mark.parametrize("cfg", [CONFIGS[0], CONFIGS[2], CONFIGS[3], CONFIGS[4]], ids=lambda c: f"D{c[0]}F{c[2]}")
def test_table_gradient_with_zero_and_partly_zero_upstream_gradients(cfg, device):
    """The table backward skips (point, level) pairs whose upstream gradient is zero (the padding
    rows of a pruned batch); pairs with one nonzero feature must still count."""
    D, L, F, T, base, scale, interp, n, (lo, hi) = cfg
    enc = HashGridEncoding(D, L, F, T, base, scale, interp, device=device)
    with torch.no_grad():
        enc.params.uniform_(-1.0, 1.0)
    g = torch.Generator().manual_seed(3)
    x = torch.rand(n, D, generator=g) * (hi - lo) + lo
    grad = torch.randn(n, L, F, generator=g)
    kind = torch.randint(0, 3, (n, L), generator=g)  # 0: all zero, 1: one feature kept, 2: all kept
    keep = torch.zeros(n, L, F)
    keep[kind == 2] = 1.0
    one = torch.nn.functional.one_hot(torch.randint(0, F, (n, L), generator=g), F).float()
    keep[kind == 1] = one[kind == 1]  # a random one of the F features
    grad = (grad * keep).reshape(n, L * F)
    grad[: n // 4] = 0.0  # whole rows without gradient, as padding rows
    (_, gp, _), (_, gp64, _) = run_both(enc, x.to(device), grad.to(device))
    assert rel_err(gp.cpu(), gp64.cpu()) < 2e-6
    # entries that only zero-gradient pairs touched get exactly zero (LazyAdam leaves them alone)
    assert torch.equal(gp.cpu() == 0, gp64.cpu() == 0)
