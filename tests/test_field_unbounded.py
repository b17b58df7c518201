"""The field with a scene contraction and with per-image appearance codes."""

import math

import pytest
import torch

from ngp_warp._reference import contraction as contraction_ref
from ngp_warp.ops.field import FieldConfig, NGPField

CFG = FieldConfig(n_levels=4, log2_hashmap_size=12, hidden=16, finest_resolution=64.0)
INNER = torch.tensor([-4.0, -3.0, -4.0, 4.0, 5.0, 4.0])


@pytest.mark.parametrize("kind", ["l2", "linf"])
def test_contracted_field_is_the_plain_field_of_the_contracted_point(kind):
    torch.manual_seed(0)
    field = NGPField(INNER, CFG, contraction=kind)
    plain = NGPField(torch.tensor([-2.0] * 3 + [2.0] * 3), CFG)
    plain.load_state_dict(field.state_dict(), strict=False)
    plain.aabb.copy_(torch.tensor([-2.0] * 3 + [2.0] * 3))
    x = torch.randn(500, 3) * torch.tensor([3.0, 30.0, 300.0])
    d = torch.nn.functional.normalize(torch.randn(500, 3), dim=-1)
    y = contraction_ref.contract(x, kind, INNER).float()
    sigma, rgb = field(x, d)
    sigma_ref, rgb_ref = plain(y, d)
    # the contracted field's log-density is shifted so that it starts nearly transparent: optical
    # depth 0.05 across the inner box (side 8 here) at h = 0
    assert field.density_shift == pytest.approx(math.log(8.0 / 0.05)) and plain.density_shift == 0.0
    torch.testing.assert_close(sigma, sigma_ref * math.exp(-field.density_shift), rtol=1e-4, atol=1e-8)
    torch.testing.assert_close(rgb, rgb_ref, rtol=1e-4, atol=1e-6)
    assert (sigma > 0).all()  # all of space is inside
    with torch.no_grad():
        torch.testing.assert_close(field.density(x), sigma.detach(), rtol=1e-4, atol=1e-6)
    sigma.sum().backward()
    assert field.encoding.params.grad.abs().sum() > 0


def test_appearance_codes_change_colour_only():
    torch.manual_seed(1)
    cfg = FieldConfig(**{**CFG.__dict__, "appearance_dim": 8})
    field = NGPField(torch.tensor([-1.0] * 3 + [1.0] * 3), cfg, n_images=5)
    with torch.no_grad():
        field.appearance.weight.normal_()
    x = torch.rand(300, 3) * 2 - 1
    d = torch.nn.functional.normalize(torch.randn(300, 3), dim=-1)
    s0, c0 = field(x, d, torch.zeros(300, dtype=torch.long))
    s3, c3 = field(x, d, torch.full((300,), 3, dtype=torch.long))
    assert torch.equal(s0, s3) and (c0 - c3).abs().max() > 1e-3
    # None uses the mean code: with code 2 the mean of the others, that is code 2
    with torch.no_grad():
        field.appearance.weight[2] = field.appearance.weight[[0, 1, 3, 4]].mean(0)
    s_mean, c_mean = field(x, d)
    _, c_two = field(x, d, torch.full((300,), 2, dtype=torch.long))
    torch.testing.assert_close(c_mean, c_two)
    assert torch.equal(s_mean, s0) and (c_mean - c0).abs().max() > 1e-3
    # the codes learn: their gradient is non-zero and they are in the weight-decayed group
    _, c = field(x, d, torch.arange(300) % 5)
    c.sum().backward()
    assert field.appearance.weight.grad.abs().sum(-1).gt(0).all()
    assert any(p is field.appearance.weight for p in field.mlp_parameters())


def test_bad_settings_raise():
    with pytest.raises(ValueError, match="n_images"):
        NGPField(INNER, FieldConfig(appearance_dim=4))
    with pytest.raises(ValueError, match="contraction"):
        NGPField(INNER, CFG, contraction="sphere")
    with pytest.raises(ValueError, match="appearance_dim"):
        FieldConfig(appearance_dim=-1).check()


def test_the_field_checks_its_box_once_so_calls_do_not_read_it():
    """The contraction reads its box (a GPU sync, fatal in CUDA-graph capture) unless told the box
    was checked: the field checks it at construction and not per call."""
    from ngp_warp.ops.contraction import contract

    x = torch.rand(16, 3) * 4 - 2
    bad = torch.tensor([0.0, 0.0, 0.0, float("nan"), 1.0, 1.0])
    with pytest.raises(ValueError, match="finite"):
        contract(x, "l2", bad)
    assert contract(x, "l2", bad, check_box=False).shape == (16, 3)  # not read
    with pytest.raises(ValueError, match="finite"):
        NGPField(bad, FieldConfig(n_levels=2, log2_hashmap_size=8), contraction="l2")


@pytest.mark.cuda
def test_contracted_density_captures_in_a_cuda_graph():
    field = NGPField(torch.tensor([-1.0, -1, -1, 1, 1, 1]), FieldConfig(n_levels=4, log2_hashmap_size=12),
                     contraction="l2").cuda()
    x = torch.rand(4096, 3, device="cuda") * 8 - 4
    with torch.no_grad():
        want = field.density(x)
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            field.density(x)  # warm-up off the capture
        torch.cuda.current_stream().wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            got = field.density(x)
        graph.replay()
    torch.cuda.synchronize()
    torch.testing.assert_close(got, want)
