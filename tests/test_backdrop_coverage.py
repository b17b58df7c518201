"""benchmarks/backdrop_coverage.py: the environment model's fit recovers what it can hold and
not a sharp edge."""

import math

import torch

from ngp_warp.ops.spherical_harmonics import spherical_harmonics_deg4

from benchmark_scripts import load_benchmark

coverage = load_benchmark("backdrop_coverage")


def directions(n: int, seed: int = 0) -> torch.Tensor:
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=torch.Generator().manual_seed(seed)), dim=1)


def test_fit_recovers_an_environment_of_its_own_form_but_not_a_horizon():
    d, held = directions(4000), directions(1000, seed=1)
    truth = torch.randn(16, 3, generator=torch.Generator().manual_seed(2)) * 0.5
    smooth = lambda x: torch.sigmoid(spherical_harmonics_deg4(x) @ truth)  # noqa: E731
    weights = coverage.fit_environment(d, smooth(d), steps=1500)
    fitted = torch.sigmoid(spherical_harmonics_deg4(held) @ weights)
    assert coverage.psnr(fitted, smooth(held)) > 40.0
    horizon = lambda x: (x[:, 2:] > 0.1 * torch.sin(12 * torch.atan2(x[:, 1:2], x[:, :1]))).float().expand(-1, 3)  # noqa: E731
    weights = coverage.fit_environment(d, horizon(d), steps=1500)
    assert coverage.psnr(torch.sigmoid(spherical_harmonics_deg4(held) @ weights), horizon(held)) < 20.0
    assert coverage.psnr(held, held) == math.inf
