"""The view directions' spherical harmonics: Warp values and hand-written gradient against the
float64 twin."""

import math

import pytest
import torch

from ngp_warp._reference import spherical_harmonics as twin
from ngp_warp.ops.field import FieldConfig, NGPField
from ngp_warp.ops.spherical_harmonics import spherical_harmonics_deg4

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)]


def test_spherical_harmonics_are_orthonormal():
    # Monte Carlo estimate of ∫ Y_i Y_j dω over the sphere = δ_ij.
    g = torch.Generator().manual_seed(1)
    d = torch.randn(400_000, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    y = twin.spherical_harmonics_deg4(d)
    gram = 4.0 * math.pi * (y.T @ y) / d.shape[0]
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=0.02)


@pytest.mark.parametrize("device", DEVICES)
def test_spherical_harmonics_kernel_matches_reference(device):
    d = torch.nn.functional.normalize(torch.randn(5000, 3, dtype=torch.float64), dim=-1)
    got = spherical_harmonics_deg4(d.float().to(device))
    assert got.dtype == torch.float32 and got.shape == (5000, 16) and got.device.type == device
    torch.testing.assert_close(got.cpu().double(), twin.spherical_harmonics_deg4(d), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("device", DEVICES)
def test_the_gradient_matches_the_twins(device):
    g = torch.Generator().manual_seed(3)
    d = torch.nn.functional.normalize(torch.randn(3000, 3, generator=g, dtype=torch.float64), dim=-1)
    weights = torch.randn(3000, 16, generator=g, dtype=torch.float64)
    d32 = d.float().to(device).t().contiguous().t().requires_grad_()  # column-major: any strides
    (spherical_harmonics_deg4(d32) * weights.float().to(device)).sum().backward()
    d64 = d.clone().requires_grad_()
    (twin.spherical_harmonics_deg4(d64) * weights).sum().backward()
    assert d64.grad.abs().mean() > 0.5
    torch.testing.assert_close(d32.grad.cpu().double(), d64.grad, rtol=1e-5, atol=1e-5)


def test_float64_directions_get_a_float64_gradient_and_no_second_derivative():
    d = torch.nn.functional.normalize(torch.randn(7, 3, dtype=torch.float64), dim=-1).requires_grad_()
    values = spherical_harmonics_deg4(d)
    assert values.dtype == torch.float32
    (grad,) = torch.autograd.grad(values.sum(), d, create_graph=True)
    assert grad.dtype == torch.float64 and grad.abs().sum() > 0
    with pytest.raises(RuntimeError, match="differentiable once"):
        grad.sum().backward()
    with torch.no_grad():
        assert not spherical_harmonics_deg4(d).requires_grad


def test_the_field_colour_reaches_the_directions():
    field = NGPField(torch.tensor([-1.0, -1, -1, 1, 1, 1]), FieldConfig(n_levels=2, log2_hashmap_size=8, hidden=16))
    x = torch.rand(6, 3) - 0.5
    d = torch.nn.functional.normalize(torch.randn(6, 3), dim=-1).requires_grad_()
    (grad,) = torch.autograd.grad(field(x, d)[1].sum(), d)
    eps, fd = 1e-2, torch.zeros(6, 3)
    with torch.no_grad():
        for k in range(3):
            step = torch.zeros(3)
            step[k] = eps
            fd[:, k] = (field(x, d + step)[1].sum(-1) - field(x, d - step)[1].sum(-1)) / (2 * eps)
    assert fd.abs().max() > 1e-3
    torch.testing.assert_close(grad, fd, rtol=0.05, atol=2e-4)
