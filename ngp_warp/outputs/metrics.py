"""Image quality metrics of the NeRF papers: PSNR and SSIM on [0, 1] images (evaluation only)."""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03


def _check(pred: torch.Tensor, gt: torch.Tensor, min_size: int = 1) -> None:
    for name, t in (("pred", pred), ("gt", gt)):
        if not isinstance(t, torch.Tensor):
            raise ValueError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
        if t.dim() != 3:
            raise ValueError(f"{name} must have shape [H, W, C], got {list(t.shape)}")
        if not t.is_floating_point():
            raise ValueError(f"{name} must be a float image in [0, 1], got {t.dtype}")
    if pred.shape != gt.shape:
        raise ValueError(f"pred and gt differ in shape: {list(pred.shape)} vs {list(gt.shape)}")
    if pred.device != gt.device:
        raise ValueError(f"pred is on {pred.device} but gt is on {gt.device}")
    if min(pred.shape[:2]) < min_size:
        raise ValueError(f"images must be at least {min_size}x{min_size} pixels, got {list(pred.shape[:2])}")


def _check_batch(pred: torch.Tensor, gt: torch.Tensor, min_size: int = 1) -> None:
    for name, t in (("pred", pred), ("gt", gt)):
        if not isinstance(t, torch.Tensor) or t.dim() != 4 or t.shape[0] == 0:
            raise ValueError(f"{name} must be a torch.Tensor of shape [N, H, W, C], N >= 1")
    if pred.shape != gt.shape:
        raise ValueError(f"pred and gt differ in shape: {list(pred.shape)} vs {list(gt.shape)}")
    _check(pred[0], gt[0], min_size)


def psnr(pred: torch.Tensor, gt: torch.Tensor) -> float:
    """Peak signal-to-noise ratio in dB for a data range of 1 (inf for identical images).

    Args:
        pred, gt: [H, W, C] float images in [0, 1].

    .. math::
        \\mathrm{PSNR} = -10 \\log_{10} \\frac{1}{HWC} \\sum (\\mathrm{pred} - \\mathrm{gt})^2
    """
    return float(psnr_tensor(pred, gt))


def psnr_tensor(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """:func:`psnr` as a 0-d float64 tensor on the images' device, computed without a host read
    (the evaluation reads a view's scores later, in one copy)."""
    _check(pred, gt)
    return psnr_batch(pred[None], gt[None])[0]


def psnr_batch(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """:func:`psnr` of N image pairs at once: pred, gt [N, H, W, C] float → [N] float64 on their
    device, without a host read (the evaluation scores a group of views in one set of launches)."""
    _check_batch(pred, gt)
    return -10.0 * torch.log10(((pred.double() - gt.double()) ** 2).flatten(1).mean(1))


@functools.lru_cache(maxsize=None)  # one per device, made once
def _gaussian_window(device: torch.device) -> torch.Tensor:
    x = torch.arange(SSIM_WINDOW, dtype=torch.float64, device=device) - (SSIM_WINDOW - 1) / 2
    w = torch.exp(-0.5 * (x / SSIM_SIGMA) ** 2)
    return w / w.sum()


def _blur(images: torch.Tensor, shifted: bool) -> torch.Tensor:
    """[N, H, W] float64 → [N, H - 10, W - 10]: the separable Gaussian window at every position
    inside the images, one pass per axis: as the window's 11 weighted shifts of the images summed
    (``shifted``; CUDA's way, where cuDNN's float64 convolutions took 3.3 ms for a 400 × 400
    view's five images on an H200) or as two convolutions (the CPU's way, in one pass over the
    data where the shifts take eleven)."""
    if not shifted:
        w = _gaussian_window(images.device)
        return F.conv2d(F.conv2d(images[:, None], w.view(1, 1, -1, 1)), w.view(1, 1, 1, -1))[:, 0]
    weights = _gaussian_window(torch.device("cpu")).tolist()  # host floats: no device read per shift
    for axis in (1, 2):
        n = images.shape[axis] - SSIM_WINDOW + 1
        blurred = images.narrow(axis, 0, n) * weights[0]
        for k in range(1, SSIM_WINDOW):
            blurred.add_(images.narrow(axis, k, n), alpha=weights[k])
        images = blurred
    return images


def ssim(pred: torch.Tensor, gt: torch.Tensor) -> float:
    """Structural similarity (Wang et al. 2004) as the NeRF papers report it: a Gaussian window
    of 11 taps, sigma 1.5, K1 0.01, K2 0.03, data range 1, population statistics, only windows
    inside the image ("valid"), averaged over pixels and channels. Equals skimage's
    ``structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
    data_range=1, channel_axis=-1)``.

    Args:
        pred, gt: [H, W, C] float images in [0, 1], H, W >= 11.

    .. math::
        \\mathrm{SSIM} = \\operatorname{mean}
        \\frac{(2\\mu_x\\mu_y + C_1)(2\\sigma_{xy} + C_2)}{(\\mu_x^2 + \\mu_y^2 + C_1)(\\sigma_x^2 + \\sigma_y^2 + C_2)},
        \\quad C_1 = K_1^2,\\ C_2 = K_2^2,

    with means and (co)variances taken under the Gaussian window.
    """
    return float(ssim_tensor(pred, gt))


def ssim_tensor(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """:func:`ssim` as a 0-d float64 tensor on the images' device, computed without a host read."""
    _check(pred, gt, SSIM_WINDOW)
    return ssim_batch(pred[None], gt[None])[0]


def ssim_batch(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """:func:`ssim` of N image pairs at once: pred, gt [N, H, W, C] float, H, W >= 11 → [N]
    float64 on their device, without a host read."""
    _check_batch(pred, gt, SSIM_WINDOW)
    n, channels = pred.shape[0], pred.shape[-1]
    x = pred.double().permute(0, 3, 1, 2).flatten(0, 1)  # [N C, H, W]
    y = gt.double().permute(0, 3, 1, 2).flatten(0, 1)
    # the five blurred images of every pair at once, one pass per axis of the separable window
    blurred = _blur(torch.cat([x, y, x * x, y * y, x * y]), shifted=x.is_cuda)
    mu_x, mu_y, xx, yy, xy = blurred.chunk(5)
    var_x = xx - mu_x**2
    var_y = yy - mu_y**2
    cov = xy - mu_x * mu_y
    c1, c2 = SSIM_K1**2, SSIM_K2**2
    s = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))
    return s.view(n, channels, *s.shape[1:]).flatten(1).mean(1)
