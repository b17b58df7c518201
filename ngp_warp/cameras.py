"""Pinhole cameras with OpenCV lens distortion: pixel -> world ray (torch, any device).

Conventions (NeRF-synthetic / instant-ngp ``transforms.json``): camera-to-world matrices in the
OpenGL / Blender convention -- the camera looks down its -z axis, +y is up, +x is right; pixel
rows grow downwards; pixel (px, py) is sampled at its centre (px + 1/2, py + 1/2).
"""

from __future__ import annotations

import torch

from ngp_warp.kernels.batch import UNDISTORT_ITERATIONS  # one count for the torch and Warp twins


def _check(t: torch.Tensor, name: str, shape: tuple, like: torch.Tensor | None = None) -> None:
    if not isinstance(t, torch.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if t.dim() != len(shape) or any(s is not None and s != n for s, n in zip(shape, t.shape)):
        want = "[" + ", ".join("B" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"{name} must have shape {want}, got {list(t.shape)}")
    if like is not None and t.device != like.device:
        raise ValueError(f"{name} is on {t.device} but c2w is on {like.device}")


def distort(x: torch.Tensor, y: torch.Tensor, distortion: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """OpenCV radial-tangential distortion of normalised image coordinates.

    Args:
        x, y: [B] float, undistorted normalised coordinates ((u - cx)/fx, (v - cy)/fy), y down.
        distortion: [B, 4] float, k1, k2, p1, p2.

    Returns:
        (xd, yd): [B] distorted coordinates,

    .. math::
        r^2 = x^2 + y^2,\\quad \\rho = k_1 r^2 + k_2 r^4,\\\\
        x_d = x (1 + \\rho) + 2 p_1 x y + p_2 (r^2 + 2 x^2),\\quad
        y_d = y (1 + \\rho) + 2 p_2 x y + p_1 (r^2 + 2 y^2).
    """
    k1, k2, p1, p2 = distortion.unbind(-1)
    r2 = x * x + y * y
    rho = r2 * (k1 + k2 * r2)
    xd = x * (1 + rho) + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * (1 + rho) + 2 * p2 * x * y + p1 * (r2 + 2 * y * y)
    return xd, yd


def undistort(xd: torch.Tensor, yd: torch.Tensor, distortion: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Invert :func:`distort` by Newton's method from (xd, yd), as instant-ngp does
    (its ``iterative_camera_undistortion``), with the analytic 2x2 Jacobian and a fixed
    :data:`UNDISTORT_ITERATIONS` steps. Zero distortion is the identity exactly.

    Args:
        xd, yd: [B] float, distorted normalised coordinates.
        distortion: [B, 4] float, k1, k2, p1, p2.

    Returns:
        (x, y): [B] with ``distort(x, y) == (xd, yd)`` to float precision,

    .. math::
        (x, y) \\leftarrow (x, y) - J^{-1} (\\mathrm{distort}(x, y) - (x_d, y_d)).
    """
    k1, k2, p1, p2 = distortion.unbind(-1)
    x, y = xd, yd
    for _ in range(UNDISTORT_ITERATIONS):
        r2 = x * x + y * y
        rho = r2 * (k1 + k2 * r2)
        drho = 2 * (k1 + 2 * k2 * r2)  # d rho / dx = drho * x
        ex = x * (1 + rho) + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - xd
        ey = y * (1 + rho) + 2 * p2 * x * y + p1 * (r2 + 2 * y * y) - yd
        jxx = 1 + rho + drho * x * x + 2 * p1 * y + 6 * p2 * x
        jxy = drho * x * y + 2 * p1 * x + 2 * p2 * y
        jyx = drho * x * y + 2 * p2 * y + 2 * p1 * x
        jyy = 1 + rho + drho * y * y + 2 * p2 * x + 6 * p1 * y
        det = jxx * jyy - jxy * jyx
        det = torch.where(det.abs() < 1e-12, torch.full_like(det, 1e-12), det)
        x = x - (jyy * ex - jxy * ey) / det
        y = y - (jxx * ey - jyx * ex) / det
    return x, y


def generate_rays(
    c2w: torch.Tensor,
    intrinsics: torch.Tensor,
    distortion: torch.Tensor | None,
    px: torch.Tensor,
    py: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """World-space rays through pixel centres.

    Args:
        c2w: [B, 3, 4] float32 (or float64) camera-to-world, OpenGL convention.
        intrinsics: [B, 4] float, fx, fy, cx, cy in pixels.
        distortion: [B, 4] float k1, k2, p1, p2, or None for an ideal pinhole (zeros give the
            same rays, after a few no-op Newton steps).
        px, py: [B] integer (or float) pixel column and row.

    Returns:
        rays_o: [B, 3] camera centres; rays_d: [B, 3] unit directions; dtype of ``c2w``, on its
        device,

    .. math::
        x_d = \\frac{p_x + 1/2 - c_x}{f_x},\\quad y_d = \\frac{p_y + 1/2 - c_y}{f_y},\\quad
        (x, y) = \\mathrm{undistort}(x_d, y_d),\\quad
        d = \\frac{R\\,(x, -y, -1)^T}{\\lVert R\\,(x, -y, -1)^T \\rVert},\\quad o = t.
    """
    _check(c2w, "c2w", (None, 3, 4))
    if not c2w.is_floating_point():
        raise ValueError(f"c2w must be a float tensor, got {c2w.dtype}")
    b = c2w.shape[0]
    _check(intrinsics, "intrinsics", (b, 4), c2w)
    _check(px, "px", (b,), c2w)
    _check(py, "py", (b,), c2w)
    if distortion is not None:
        _check(distortion, "distortion", (b, 4), c2w)
    dtype = c2w.dtype
    intr = intrinsics.to(dtype)
    x = (px.to(dtype) + 0.5 - intr[:, 2]) / intr[:, 0]
    y = (py.to(dtype) + 0.5 - intr[:, 3]) / intr[:, 1]
    if distortion is not None:
        x, y = undistort(x, y, distortion.to(dtype))
    rot = c2w[:, :, :3]
    d = rot[:, :, 0] * x[:, None] - rot[:, :, 1] * y[:, None] - rot[:, :, 2]
    d = d / d.norm(dim=-1, keepdim=True)
    return c2w[:, :, 3].contiguous(), d
