import math

import pytest
import torch

from ngp_warp.ops.field import FieldConfig, NGPField, density_from_log, trunc_exp


def test_trunc_exp_gradient_is_clamped():
    x = torch.tensor([0.5, 20.0], requires_grad=True)
    trunc_exp(x).sum().backward()
    assert torch.allclose(x.grad, torch.exp(torch.tensor([0.5, 15.0])))


def test_field_shapes_and_gradients():
    cfg = FieldConfig(n_levels=4, log2_hashmap_size=12, finest_resolution=64.0, hidden=16)
    field = NGPField(torch.tensor([-1.0, -1, -1, 1, 1, 1]), cfg)
    torch.nn.init.uniform_(field.encoding.params, -1.0, 1.0)
    x = torch.rand(100, 3) * 2 - 1
    d = torch.nn.functional.normalize(torch.randn(100, 3), dim=-1)
    sigma, rgb = field(x, d)
    assert sigma.shape == (100,) and rgb.shape == (100, 3)
    assert (sigma > 0).all() and ((rgb > 0) & (rgb < 1)).all()
    (sigma.sum() + rgb.sum()).backward()
    assert field.encoding.params.grad.abs().sum() > 0
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in field.mlp_parameters())
    # Density ignores direction; colour does not.
    sigma2, rgb2 = field(x, -d)
    assert torch.equal(sigma, sigma2) and not torch.allclose(rgb, rgb2)
    # Density is zero outside the box.
    assert (field.density(torch.full((3, 3), 1.5)) == 0).all()


def test_field_runs_under_autocast():
    cfg = FieldConfig(n_levels=4, log2_hashmap_size=12, finest_resolution=64.0, hidden=16)
    field = NGPField(torch.tensor([-1.0, -1, -1, 1, 1, 1]), cfg)
    x = torch.rand(64, 3) * 2 - 1
    d = torch.nn.functional.normalize(torch.randn(64, 3), dim=-1)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        sigma, rgb = field(x, d)
    assert sigma.dtype == torch.float32 and rgb.dtype == torch.float32
    (sigma.sum() + rgb.sum()).backward()
    assert field.density_mlp[0].weight.grad is not None and field.encoding.params.grad is not None


def _small_field(device="cpu"):
    cfg = FieldConfig(n_levels=4, log2_hashmap_size=12, finest_resolution=64.0, hidden=16)
    field = NGPField(torch.tensor([-1.0, -1, -1, 1, 1, 1]), cfg).to(device)
    torch.nn.init.uniform_(field.encoding.params, -1.0, 1.0)
    return field


def test_fused_density_mlp_matches_the_module_mlp():
    """The no-grad density MLP (fused ReLU epilogues) equals the modules' output, all G columns
    and the first alone (density's CUDA path), with some ReLUs active and some not."""
    field = _small_field()
    x = torch.rand(500, 3) * 2 - 1
    with torch.no_grad():
        want = field._geometry(x)
        hidden = field.density_mlp[1](field.density_mlp[0](field._features(x)))
        got = field._geometry_no_grad(x)
        first = field._geometry_no_grad(x, 1)
    assert got.shape == (500, 16) and first.shape == (500, 1) and 0.1 < (hidden > 0).float().mean() < 0.9
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(first, want[:, :1], rtol=1e-5, atol=1e-6)


def _field_with(contraction, appearance_dim):
    cfg = FieldConfig(n_levels=4, log2_hashmap_size=12, finest_resolution=64.0, hidden=16,
                      appearance_dim=appearance_dim)
    field = NGPField(torch.tensor([-1.0, -1, -1, 1, 1, 1]), cfg, contraction=contraction, n_images=3)
    torch.nn.init.uniform_(field.encoding.params, -1.0, 1.0)
    if appearance_dim:
        torch.nn.init.normal_(field.appearance.weight, std=1.0)  # codes that change the colour
    return field


@pytest.mark.parametrize("contraction", [None, "l2"])
@pytest.mark.parametrize("appearance_dim", [0, 4])
def test_geometry_then_colour_equals_forward(contraction, appearance_dim):
    field = _field_with(contraction, appearance_dim)
    x = torch.randn(600, 3) * (3.0 if contraction else 0.7)  # some outside the box
    d = torch.nn.functional.normalize(torch.randn(600, 3), dim=-1)
    with torch.no_grad():
        sigma_want, rgb_want = field(x, d)
    sigma, h = field.geometry(x)
    assert sigma.dtype == torch.float32 and h.shape == (600, 16) and sigma.shape == (600,)
    assert (sigma > 0).any() and (contraction is not None or (sigma == 0).any())
    torch.testing.assert_close(sigma, sigma_want, rtol=1e-5, atol=1e-7)
    rgb = field.colour(h, d)
    assert rgb.dtype == torch.float32 and rgb.shape == (600, 3)
    torch.testing.assert_close(rgb, rgb_want, rtol=1e-5, atol=1e-6)
    assert not torch.allclose(field.colour(h, -d), rgb_want, atol=1e-3)  # the comparison can fail
    if appearance_dim:
        with torch.no_grad():
            second = field(x, d, torch.full((600,), 2))[1]
        torch.testing.assert_close(field.colour(h, d, field.appearance.weight[2]), second, rtol=1e-5, atol=1e-6)
        assert (second - rgb_want).abs().max() > 1e-3  # image 2's code is not the mean one
    code = field.appearance.weight[2].detach().clone().requires_grad_(True) if appearance_dim else None
    h_leaf = h.detach().clone().requires_grad_(True)
    rgb_grad = field.colour(h_leaf, d, code, differentiable=True)
    assert rgb_grad.requires_grad and not field.colour(h_leaf, d, code).requires_grad
    torch.testing.assert_close(rgb_grad, field.colour(h, d, code), rtol=1e-5, atol=1e-6)
    weights = torch.rand(600, 3)
    rgb_grad.mul(weights).sum().backward()
    assert h_leaf.grad.abs().sum() > 0
    if appearance_dim:  # the code's gradient is the training path's gradient of image 2's code
        field.zero_grad()
        field(x, d, torch.full((600,), 2))[1].mul(weights).sum().backward()
        assert code.grad.abs().sum() > 0
        torch.testing.assert_close(code.grad, field.appearance.weight.grad[2], rtol=1e-4, atol=1e-6)


def test_appearance_code_is_checked():
    with pytest.raises(ValueError, match="no appearance codes"):
        _field_with(None, 0).appearance_code(torch.zeros(4))
    field = _field_with(None, 4)
    with pytest.raises(ValueError, match=r"\[4\] float"):
        field.appearance_code(torch.zeros(3))
    torch.testing.assert_close(field.appearance_code(None), field.appearance.weight.mean(0))
    assert _field_with(None, 0).appearance_code(None) is None
    with pytest.raises(ValueError, match="colour needs h"):
        field.colour(torch.zeros(5, 15), torch.zeros(5, 3))


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_density_from_log_is_exp_inside_the_box_and_zero_outside(dtype, device):
    aabb = torch.tensor([-1.0, -0.5, -2.0, 1.0, 0.5, 2.0], device=device)
    x = (torch.rand(3000, 3, device=device) * 2.4 - 1.2) * aabb[3:]
    x[:3] = aabb[:3]  # the box's faces are inside
    x[3:6] = aabb[3:]
    h = (torch.randn(3000, 1, device=device) * 3).to(dtype)
    sigma = density_from_log(h, x, aabb)
    inside = ((x >= aabb[:3]) & (x <= aabb[3:])).all(-1)
    assert 0.2 < inside.float().mean() < 0.9 and inside[:6].all()
    want = torch.where(inside, h.double().exp().reshape(-1), 0.0)
    assert sigma.dtype == torch.float32 and sigma.shape == (3000,)
    torch.testing.assert_close(sigma.double(), want, rtol=1e-6, atol=0)
    with pytest.raises(ValueError, match="log_sigma"):
        density_from_log(h[:-1], x, aabb)


@pytest.mark.cuda
def test_cuda_density_without_grad_matches_the_field():
    field = _small_field("cuda")
    x = torch.rand(4096, 3, device="cuda") * 2.2 - 1.1  # some outside the box
    with torch.no_grad():
        sigma = field(x, torch.nn.functional.normalize(torch.randn_like(x), dim=-1))[0]
        fused = field.density(x)
        torch.testing.assert_close(fused, sigma, rtol=1e-5, atol=1e-5)
        with torch.autocast("cuda", dtype=torch.bfloat16):
            sigma16 = field(x, x)[0]
            fused16 = field.density(x)
        with torch.autocast("cuda"):  # float16 h takes the float32 kernel
            fused_half = field.density(x)
    assert (fused == 0).any() and fused16.dtype == torch.float32
    torch.testing.assert_close(fused16, sigma16, rtol=0.05, atol=0.05)
    torch.testing.assert_close(fused_half, sigma, rtol=0.01, atol=0.01)
