"""PSNR and SSIM against closed forms and an independent direct-summation SSIM."""

import math

import numpy as np
import pytest
import torch

from ngp_warp.outputs.metrics import psnr, psnr_batch, ssim, ssim_batch


def _images(h=32, w=40, c=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(h, w, c, generator=g)
    # a structured image plus noise, so windows see real variance and covariance
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    base = (0.5 + 0.4 * torch.sin(6 * xx + 3 * yy))[..., None].expand(h, w, c)
    y = (0.7 * base + 0.3 * x).clamp(0, 1)
    return x, y


def _ssim_direct(a: np.ndarray, b: np.ndarray) -> float:
    """SSIM by explicit weighted sums over every 11x11 window inside the image (2-D weights,
    no separable filtering), float64; the mean over windows and channels."""
    r = 5
    t = np.arange(-r, r + 1)
    g = np.exp(-(t[:, None] ** 2 + t[None, :] ** 2) / (2 * 1.5**2))
    g /= g.sum()
    c1, c2 = 0.01**2, 0.03**2
    h, w, c = a.shape
    vals = []
    for k in range(c):
        for i in range(r, h - r):
            for j in range(r, w - r):
                pa = a[i - r:i + r + 1, j - r:j + r + 1, k]
                pb = b[i - r:i + r + 1, j - r:j + r + 1, k]
                ma, mb = (g * pa).sum(), (g * pb).sum()
                va, vb = (g * (pa - ma) ** 2).sum(), (g * (pb - mb) ** 2).sum()
                cov = (g * (pa - ma) * (pb - mb)).sum()
                vals.append((2 * ma * mb + c1) * (2 * cov + c2) / ((ma**2 + mb**2 + c1) * (va + vb + c2)))
    return float(np.mean(vals))


def test_psnr_closed_forms():
    x, _ = _images()
    assert psnr(x, x) == math.inf
    gt = torch.full((8, 9, 3), 0.25)
    assert psnr(gt + 0.1, gt) == pytest.approx(20.0, abs=1e-5)  # -10 log10(0.01)
    pred = gt.clone()
    pred[0, 0, 0] += 0.5  # one error of 0.5 among 216 values
    assert psnr(pred, gt) == pytest.approx(-10 * math.log10(0.25 / 216), abs=1e-5)


def test_psnr_matches_mse_definition_on_random_images():
    x, y = _images(seed=1)
    mse = float(((x.double() - y.double()) ** 2).mean())
    assert psnr(x, y) == pytest.approx(-10 * math.log10(mse), rel=1e-12)
    assert psnr(x, y) == psnr(y, x)


def test_ssim_identical_and_constant_images():
    x, _ = _images()
    assert ssim(x, x) == pytest.approx(1.0, abs=1e-12)
    a, b = 0.2, 0.7  # constant images: only the luminance term differs from 1
    c1 = 0.01**2
    want = (2 * a * b + c1) / (a * a + b * b + c1)
    assert ssim(torch.full((16, 16, 3), a), torch.full((16, 16, 3), b)) == pytest.approx(want, rel=1e-6)


@pytest.mark.parametrize("seed", [0, 1])
def test_ssim_matches_direct_summation(seed):
    x, y = _images(h=20, w=23, seed=seed)
    want = _ssim_direct(x.double().numpy(), y.double().numpy())
    assert 0.05 < want < 0.95  # a non-trivial value
    assert ssim(x, y) == pytest.approx(want, abs=1e-10)
    assert ssim(y, x) == pytest.approx(want, abs=1e-10)


def test_the_shifted_blur_equals_the_convolutions():
    """SSIM's blur on CUDA (the window's weighted shifts summed) and elsewhere (convolutions) agree."""
    from ngp_warp.outputs.metrics import _blur

    images = torch.rand(5, 17, 26, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    shifted, convolved = _blur(images, shifted=True), _blur(images, shifted=False)
    assert shifted.shape == (5, 7, 16)
    torch.testing.assert_close(shifted, convolved, rtol=0, atol=1e-14)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_ssim_on_cuda_equals_the_cpu():
    x, y = _images(h=40, w=53, seed=5)
    assert ssim(x.cuda(), y.cuda()) == pytest.approx(ssim(x, y), abs=1e-12)


def test_ssim_matches_scipy_gaussian_filter_formulation():
    """skimage's formulation (scipy.ndimage Gaussian, truncate 3.5, borders cropped by 5)."""
    ndimage = pytest.importorskip("scipy.ndimage")
    x, y = _images(seed=2)
    a, b = x.double().numpy(), y.double().numpy()

    def blur(t):
        return ndimage.gaussian_filter(t, sigma=1.5, truncate=3.5, mode="reflect")[5:-5, 5:-5]

    c1, c2 = 0.01**2, 0.03**2
    per_channel = []
    for k in range(3):
        u, v = a[..., k], b[..., k]
        mu, mv = blur(u), blur(v)
        vu, vv, cov = blur(u * u) - mu**2, blur(v * v) - mv**2, blur(u * v) - mu * mv
        s = (2 * mu * mv + c1) * (2 * cov + c2) / ((mu**2 + mv**2 + c1) * (vu + vv + c2))
        per_channel.append(s.mean())
    assert ssim(x, y) == pytest.approx(float(np.mean(per_channel)), abs=1e-10)


def test_metrics_validate_inputs():
    x, y = _images()
    for bad in ((x, y[:-1]), (x[..., 0], y[..., 0]), (x, (y * 255).to(torch.uint8)), (x.numpy(), y)):
        with pytest.raises(ValueError):
            psnr(*bad)
        with pytest.raises(ValueError):
            ssim(*bad)
    with pytest.raises(ValueError, match="at least 11x11"):
        ssim(x[:10], y[:10])


@pytest.mark.parametrize("size", [(11, 11), (17, 23)])
def test_a_batch_of_pairs_scores_as_each_pair_alone(size):
    gen = torch.Generator().manual_seed(5)
    pred = torch.rand(3, *size, 3, generator=gen)
    gt = (pred + 0.1 * torch.randn(3, *size, 3, generator=gen)).clamp(0, 1)
    psnrs, ssims = psnr_batch(pred, gt), ssim_batch(pred, gt)
    assert psnrs.shape == ssims.shape == (3,) and psnrs.dtype == ssims.dtype == torch.float64
    for k in range(3):
        assert psnrs[k].item() == pytest.approx(psnr(pred[k], gt[k]), rel=1e-12)
        assert ssims[k].item() == pytest.approx(ssim(pred[k], gt[k]), rel=1e-12)
    assert len(set(psnrs.tolist())) == 3 and len(set(ssims.tolist())) == 3  # each pair its own


def test_a_batch_of_another_shape_is_refused():
    with pytest.raises(ValueError, match=r"\[N, H, W, C\]"):
        psnr_batch(torch.rand(8, 8, 3), torch.rand(8, 8, 3))
    with pytest.raises(ValueError, match="differ in shape"):
        ssim_batch(torch.rand(2, 12, 12, 3), torch.rand(3, 12, 12, 3))
