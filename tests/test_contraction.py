"""Scene contraction: Warp kernels vs the float64 twin, from the inner region to 1e6 and beyond."""

import math

import pytest
import torch

from ngp_warp.ops import contraction as C
from ngp_warp._reference import contraction as ref

KINDS = ("l2", "linf")
BOX = torch.tensor([-1.0, -0.5, -2.0, 3.0, 1.5, 0.0])  # off-centre, unequal half extents (2, 1, 1)


def _points(n_per_scale=200, seed=0):
    """Random directions at radii spanning 1e-3 .. 1e6 (normalised units), both sides of the
    unit boundary at 1 ± 1e-4, exactly on it, and the origin."""
    g = torch.Generator().manual_seed(seed)
    radii = [1e-3, 0.3, 0.9, 1 - 1e-4, 1.0, 1 + 1e-4, 1.5, 3.0, 10.0, 1e2, 1e3, 1e4, 1e6]
    dirs = torch.randn(len(radii) * n_per_scale, 3, generator=g, dtype=torch.float64)
    scale = torch.tensor(radii, dtype=torch.float64).repeat_interleave(n_per_scale)
    jitter = 1 + 1e-3 * torch.rand(len(scale), generator=g, dtype=torch.float64) * (scale > 1.5)
    x = dirs / dirs.norm(dim=-1, keepdim=True) * (scale * jitter)[:, None]
    return torch.cat([x, torch.zeros(1, 3, dtype=torch.float64)]).float()


def _world(x, aabb):
    c, h = (aabb[:3] + aabb[3:]) / 2, (aabb[3:] - aabb[:3]) / 2
    return c + h * x


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("boxed", [False, True])
def test_contract_matches_float64_twin(kind, boxed):
    aabb = BOX if boxed else None
    p = _world(_points(), BOX) if boxed else _points()
    got = C.contract(p, kind, aabb)
    want = ref.contract(p, kind, aabb)
    assert got.dtype == torch.float32 and got.shape == p.shape
    assert (got.double() - want).abs().max() < 1e-6
    n = torch.linalg.vector_norm(want, ord=2 if kind == "l2" else math.inf, dim=-1)
    assert n.max() < 2 and n.max() > 1.999 and (n < 1).any() and (n > 1.5).any()


@pytest.mark.parametrize("kind", KINDS)
def test_contraction_is_identity_inside_and_radial_outside(kind):
    x = _points()
    y = C.contract(x, kind).double()
    ord_ = 2 if kind == "l2" else math.inf
    m = torch.linalg.vector_norm(x.double(), ord=ord_, dim=-1)
    inside = m <= 1
    assert inside.sum() > 500 and torch.equal(y[inside], x.double()[inside])
    far = m > 1.5
    cos = torch.nn.functional.cosine_similarity(y[far], x.double()[far], dim=-1)
    assert (cos > 1 - 1e-6).all()  # same direction
    n = torch.linalg.vector_norm(y[far], ord=ord_, dim=-1)
    assert (n - (2 - 1 / m[far])).abs().max() < 1e-6  # ‖C(x)‖ = 2 - 1/‖x‖


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("boxed", [False, True])
def test_uncontract_matches_twin_and_inverts(kind, boxed):
    aabb = BOX if boxed else None
    x = _points()
    p = _world(x, BOX) if boxed else x
    y = C.contract(p, kind, aabb)
    back = C.uncontract(y, kind, aabb).double()
    twin = ref.uncontract(y, kind, aabb)
    m = torch.linalg.vector_norm(x.double(), ord=2 if kind == "l2" else math.inf, dim=-1)
    # 2 - ‖y‖ ~ 1/m carries the float32 rounding of ‖y‖: the relative error grows like m
    rel = ((back - twin).norm(dim=-1) / twin.norm(dim=-1).clamp_min(1e-3))
    assert (rel <= 1e-6 * (1 + m)).all()
    rel = (back - p.double()).norm(dim=-1) / p.double().norm(dim=-1).clamp_min(1e-3)
    assert (rel[m <= 1e3] < 1e-3).all() and (rel[m <= 1] < 1e-6).all()


@pytest.mark.parametrize("kind", KINDS)
def test_uncontract_clamps_the_boundary(kind):
    y = torch.tensor([[2.0, 0.0, 0.0], [0.0, -3.0, 0.0], [2.5, 2.5, -2.5]])
    x = C.uncontract(y, kind).double()
    assert torch.isfinite(x).all()
    n = torch.linalg.vector_norm(x, ord=2 if kind == "l2" else math.inf, dim=-1)
    assert ((n - 2.0**20).abs() / 2.0**20 < 1e-3).all()
    assert (torch.nn.functional.cosine_similarity(x, y.double(), dim=-1) > 1 - 1e-9).all()
    assert (x.double() - ref.uncontract(y, kind)).abs().div(2.0**20).max() < 1e-5


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("boxed", [False, True])
def test_world_step_length_matches_autograd_jvp_of_the_twin(kind, boxed):
    aabb = BOX if boxed else None
    x = _points(seed=1)
    p = _world(x, BOX) if boxed else x
    d = torch.nn.functional.normalize(torch.randn(len(p), 3), dim=-1)
    got = C.world_step_length(p, d, 0.01, kind, aabb).double()
    want = ref.world_step_length(p, d, 0.01, kind, aabb)
    assert ((got / want - 1).abs() < 2e-5).all()
    m = torch.linalg.vector_norm(x.double(), ord=2 if kind == "l2" else math.inf, dim=-1)
    # far steps grow between ‖x‖/2 (across the radius) and ‖x‖² (along it) times Δy
    assert got[m > 1e3].min() > 0.4 * 1e3 * 0.01 and got[m > 1e3].max() > 1e5 * 0.01
    if not boxed:  # the identity region: Δt = Δy along unit d
        assert (got[m < 1 - 1e-3] - 0.01).abs().max() < 1e-8


@pytest.mark.parametrize("kind", KINDS)
def test_world_step_length_is_the_contracted_spacing_to_first_order(kind):
    """A world step of Δt from p spans Δy in contracted space, up to O(Δy²) terms."""
    g = torch.Generator().manual_seed(3)
    p = torch.randn(300, 3, generator=g) * torch.logspace(0, 3, 300)[:, None]
    d = torch.nn.functional.normalize(torch.randn(300, 3, generator=g), dim=-1)
    dt = C.world_step_length(p, d, 1e-3, kind, BOX).double()
    y0 = ref.contract(p.double(), kind, BOX)
    y1 = ref.contract(p.double() + dt[:, None] * d.double(), kind, BOX)
    assert ((y1 - y0).norm(dim=-1) / 1e-3 - 1).abs().max() < 0.05


def test_validation_is_one_clear_error():
    x = torch.rand(4, 3)
    bad = [
        lambda: C.contract(x.double()),
        lambda: C.contract(x[:, :2]),
        lambda: C.contract(x, "l1"),
        lambda: C.contract(x, aabb=torch.tensor([0.0, 0, 0, 1, 1])),
        lambda: C.contract(x, aabb=torch.tensor([0.0, 0, 0, 1, -1, 1])),
        lambda: C.uncontract(x.requires_grad_()),
        lambda: C.world_step_length(x, torch.rand(3, 3), 0.1),
        lambda: C.world_step_length(x, torch.rand(4, 3), 0.0),
        lambda: C.world_step_length(x, torch.rand(4, 3), float("nan")),
    ]
    for call in bad:
        with pytest.raises(ValueError) as e:
            call()
        assert "\n" not in str(e.value)
    with torch.no_grad():
        assert C.contract(x.requires_grad_()).shape == (4, 3)
    assert C.contract(torch.empty(0, 3)).shape == (0, 3)


@pytest.mark.parametrize("kind", KINDS)
def test_points_of_any_strides(kind):
    p = _points(20)
    for strided in (p.t().contiguous().t(), torch.cat([p[:, :1], p], 1)[:, 1:]):  # column-major, an offset view
        assert torch.equal(C.contract(strided, kind), C.contract(p, kind))
        y = C.contract(p, kind)
        assert torch.equal(C.uncontract(y.t().contiguous().t(), kind), C.uncontract(y, kind))


def test_a_contracted_field_refuses_positions_that_need_a_gradient():
    from ngp_warp.ops.field import FieldConfig, NGPField

    box = torch.tensor([-1.0, -1, -1, 1, 1, 1])
    field = NGPField(box, FieldConfig(n_levels=2, log2_hashmap_size=8), contraction="l2")
    x, d = torch.rand(5, 3, requires_grad=True), torch.nn.functional.normalize(torch.randn(5, 3), dim=-1)
    with pytest.raises(ValueError, match="requires grad, but contraction has no backward"):
        field(x, d)
    sigma, rgb = field(x.detach(), d)
    assert sigma.shape == (5,) and rgb.shape == (5, 3)


@pytest.mark.cuda
@pytest.mark.parametrize("kind", KINDS)
def test_cuda_matches_cpu(kind):
    p = _world(_points(), BOX)
    d = torch.nn.functional.normalize(torch.randn(len(p), 3), dim=-1)
    box = BOX.cuda()
    y = C.contract(p, kind, BOX)
    for cpu, gpu in (
        (y, C.contract(p.cuda(), kind, box)),
        (C.world_step_length(p, d, 0.01, kind, BOX), C.world_step_length(p.cuda(), d.cuda(), 0.01, kind, box)),
    ):
        assert torch.allclose(cpu, gpu.cpu(), rtol=1e-5, atol=1e-6)
    # The inverse is ill-conditioned near the radius-2 boundary (an ulp of ‖y‖ there moves the
    # world point by ~2^-23 / (2 − ‖y‖) of its distance): compare it in world space where
    # 2 − ‖y‖ ≥ 0.01, and everywhere through the contraction (the two backends' world points
    # contract to the same y).
    back_cpu, back_gpu = C.uncontract(y, kind, BOX), C.uncontract(y.cuda(), kind, box).cpu()
    radius = y.norm(dim=-1) if kind == "l2" else y.abs().amax(-1)
    tame = radius <= 1.99
    assert tame.sum() > len(p) // 2 and (~tame).sum() > 100
    assert torch.allclose(back_cpu[tame], back_gpu[tame], rtol=1e-5, atol=1e-6)
    assert torch.allclose(C.contract(back_gpu, kind, BOX), C.contract(back_cpu, kind, BOX), rtol=0, atol=1e-5)
    # everywhere, within 64 float32 ulps of ‖y‖ carried through 1 / (2 − ‖y‖)
    allowed = 1e-5 + 64 * 2.0**-23 / (2 - radius).clamp_min(2.0**-20)
    assert ((back_cpu - back_gpu).norm(dim=-1) <= 1e-6 + allowed * back_cpu.norm(dim=-1)).all()


@pytest.mark.parametrize("box", [[0.0, 0.0, 0.0, 1.0, -1.0, 1.0], [0.0, 0.0, 0.0, 1.0, float("nan"), 1.0],
                                 [0.0, 0.0, 0.0, 1.0, 1.0, 0.0]])
def test_boxes_without_volume_are_refused_everywhere(box):
    """contract/uncontract, the field and the occupancy grid share one check of their box's values."""
    from ngp_warp.ops.field import FieldConfig, NGPField
    from ngp_warp.ops.occupancy import OccupancyGrid

    aabb = torch.tensor(box)
    x = torch.rand(4, 3)
    makers = [lambda: C.contract(x, "l2", aabb), lambda: C.uncontract(x, "l2", aabb),
              lambda: NGPField(aabb, FieldConfig(log2_hashmap_size=12, finest_resolution=32.0)),
              lambda: OccupancyGrid(aabb, resolution=8)]
    for make in makers:
        with pytest.raises(ValueError, match="aabb must be finite with max > min on every axis"):
            make()
    C.contract(x, "l2", aabb, check_box=False)  # callers that checked their box once skip it
