"""Float64 forward camera models (world -> pixel), the closed forms that
:mod:`ngp_warp.data.cameras` and the Warp ray kernel invert. Tests only."""

from __future__ import annotations

import torch


def distort(x: torch.Tensor, y: torch.Tensor, distortion: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """OpenCV radial-tangential distortion of normalised coordinates.

    Args:
        x, y: [B] float64 undistorted normalised coordinates, y down.
        distortion: [B, 6] float64 k1, k2, k3, k4, p1, p2 (k4 unused).

    Returns:
        (xd, yd) [B]: r² = x² + y², ρ = k1 r² + k2 r⁴ + k3 r⁶,
        xd = x (1 + ρ) + 2 p1 x y + p2 (r² + 2x²), yd = y (1 + ρ) + 2 p2 x y + p1 (r² + 2y²).
    """
    k1, k2, k3, _, p1, p2 = distortion.unbind(-1)
    r2 = x * x + y * y
    rho = k1 * r2 + k2 * r2**2 + k3 * r2**3
    return (x * (1 + rho) + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * (1 + rho) + 2 * p2 * x * y + p1 * (r2 + 2 * y * y))


def fisheye_distort(ray: torch.Tensor, distortion: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """OpenCV fisheye (equidistant) projection of camera-frame rays.

    Args:
        ray: [B, 3] float64 directions in OpenCV camera axes (x right, y down, z forward).
        distortion: [B, 6] float64 k1, k2, k3, k4 (p1, p2 unused).

    Returns:
        (xd, yd) [B]: θ = atan2(|(x, y)|, z), θd = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸),
        (xd, yd) = θd (x, y) / |(x, y)|.
    """
    k1, k2, k3, k4 = distortion[:, :4].unbind(-1)
    rho = ray[:, :2].norm(dim=-1)
    theta = torch.atan2(rho, ray[:, 2])
    theta_d = theta * (1 + k1 * theta**2 + k2 * theta**4 + k3 * theta**6 + k4 * theta**8)
    return theta_d * ray[:, 0] / rho, theta_d * ray[:, 1] / rho


def project(points: torch.Tensor, c2w: torch.Tensor, intrinsics: torch.Tensor, distortion: torch.Tensor | None,
            fisheye: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel coordinates (u, v) of world points, pixel centres at integer + 1/2.

    Args:
        points: [B, 3] float64 world points (in front of the camera for the pinhole models).
        c2w: [B, 3, 4] float64 OpenGL camera-to-world (camera looks down -z, +y up).
        intrinsics: [B, 4] float64 fx, fy, cx, cy.
        distortion: [B, 6] float64 k1, k2, k3, k4, p1, p2, or None (pinhole).
        fisheye: project with :func:`fisheye_distort` instead of :func:`distort`.

    Returns:
        (u, v) [B]: cam = R^T (p - t) in OpenCV axes (x, -y, -z of the OpenGL camera frame);
        (xd, yd) from the lens model; u = fx xd + cx, v = fy yd + cy.
    """
    local = torch.einsum("bji,bj->bi", c2w[:, :, :3], points - c2w[:, :, 3])
    cam = local * torch.tensor([1.0, -1.0, -1.0], dtype=local.dtype)
    if fisheye:
        xd, yd = fisheye_distort(cam, distortion)
    else:
        x, y = cam[:, 0] / cam[:, 2], cam[:, 1] / cam[:, 2]
        xd, yd = (x, y) if distortion is None else distort(x, y, distortion)
    return intrinsics[:, 0] * xd + intrinsics[:, 2], intrinsics[:, 1] * yd + intrinsics[:, 3]
