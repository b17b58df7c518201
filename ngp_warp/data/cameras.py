"""Cameras with OpenCV lenses: pixel -> world ray (torch, any device), and every pixel of one
view in one Warp launch (:func:`view_rays`, the inference renderer's).

Lenses: the ideal pinhole, OpenCV's radial-tangential model (k1 k2 k3 p1 p2) and OpenCV's
fisheye (equidistant, k1..k4); distortion vectors are [6] k1, k2, k3, k4, p1, p2. The forward
(world -> pixel) models are in :mod:`ngp_warp._reference.cameras`.

Conventions (NeRF-synthetic / instant-ngp ``transforms.json``): camera-to-world matrices in the
OpenGL / Blender convention -- the camera looks down its -z axis, +y is up, +x is right; pixel
rows grow downwards; pixel (px, py) is sampled at its centre (px + 1/2, py + 1/2).
"""

from __future__ import annotations

import torch

from ngp_warp import _wp
from ngp_warp.kernels import batch as K

# one iteration count and one set of lens codes for the torch and Warp twins
from ngp_warp.kernels.batch import LENS_FISHEYE, LENS_OPENCV, LENS_PINHOLE, UNDISTORT_ITERATIONS

__all__ = ["generate_rays", "view_rays", "undistort", "fisheye_ray", "pinhole_border_error", "LENS_PINHOLE", "LENS_OPENCV", "LENS_FISHEYE"]


def _check(t: torch.Tensor, name: str, shape: tuple, like: torch.Tensor | None = None) -> None:
    if not isinstance(t, torch.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if t.dim() != len(shape) or any(s is not None and s != n for s, n in zip(shape, t.shape)):
        want = "[" + ", ".join("B" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"{name} must have shape {want}, got {list(t.shape)}")
    if like is not None and t.device != like.device:
        raise ValueError(f"{name} is on {t.device} but c2w is on {like.device}")


def _check_lens(distortion: torch.Tensor | None, shape: tuple, fisheye: bool, like: torch.Tensor | None = None) -> None:
    """``distortion`` of ``shape`` (as :func:`_check`), or None, which a fisheye lens refuses."""
    if distortion is not None:
        _check(distortion, "distortion", shape, like)
    elif fisheye:
        raise ValueError("fisheye rays need the distortion coefficients (zeros for the plain equidistant lens)")


def undistort(xd: torch.Tensor, yd: torch.Tensor, distortion: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Invert OpenCV's radial-tangential distortion by Newton's method from (xd, yd), as
    instant-ngp does (its ``iterative_camera_undistortion``), with the analytic 2x2 Jacobian and
    a fixed :data:`UNDISTORT_ITERATIONS` steps. Zero distortion is the identity exactly.

    Args:
        xd, yd: [B] float, distorted normalised coordinates ((u - cx)/fx, (v - cy)/fy), y down.
        distortion: [B, 6] float, k1, k2, k3, k4, p1, p2 (k4 unused).

    Returns:
        (x, y): [B] with ``distort(x, y) == (xd, yd)`` to float precision
        (:func:`ngp_warp._reference.cameras.distort`),

    .. math::
        r^2 = x^2 + y^2,\\quad \\rho = k_1 r^2 + k_2 r^4 + k_3 r^6,\\\\
        \\mathrm{distort}(x, y) = (x (1 + \\rho) + 2 p_1 x y + p_2 (r^2 + 2 x^2),\\;
        y (1 + \\rho) + 2 p_2 x y + p_1 (r^2 + 2 y^2)),\\\\
        (x, y) \\leftarrow (x, y) - J^{-1} (\\mathrm{distort}(x, y) - (x_d, y_d)).
    """
    k1, k2, k3, _, p1, p2 = distortion.unbind(-1)
    x, y = xd, yd
    for _ in range(UNDISTORT_ITERATIONS):
        r2 = x * x + y * y
        rho = r2 * (k1 + r2 * (k2 + k3 * r2))
        drho = 2 * (k1 + r2 * (2 * k2 + 3 * k3 * r2))  # d rho / dx = drho * x
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


def pinhole_border_error(intrinsics: torch.Tensor, distortion: torch.Tensor, width: int, height: int,
                         samples: int = 64) -> float:
    """The most pixels by which the pinhole projection of a radial-tangential lens's ray misses
    its pixel, over ``samples`` points on each side of the image border: how far a pinhole test
    of what an image holds must grow the image (for a lens that does not fold, the pixels inside
    the image map inside the border's image).

    Args:
        intrinsics: [N, 4] float fx, fy, cx, cy. distortion: [N, 6] float k1, k2, k3, k4, p1, p2.
        width, height: image size in pixels.
    """
    t = torch.linspace(0.0, 1.0, samples, dtype=torch.float64)
    zeros, ones = torch.zeros_like(t), torch.ones_like(t)
    u = torch.cat([t, t, zeros, ones]) * width
    v = torch.cat([zeros, ones, t, t]) * height
    fx, fy, cx, cy = intrinsics.detach().cpu().double()[:, None, :].unbind(-1)  # each [N, 1]
    xd, yd = (u - cx) / fx, (v - cy) / fy  # [N, 4·samples]
    lens = distortion.detach().cpu().double()[:, None, :].expand(-1, u.numel(), -1).reshape(-1, 6)
    x, y = undistort(xd.reshape(-1), yd.reshape(-1), lens)
    error = torch.maximum((x.reshape(xd.shape) - xd).abs() * fx, (y.reshape(yd.shape) - yd).abs() * fy)
    return float(error.max())


def fisheye_ray(xd: torch.Tensor, yd: torch.Tensor, distortion: torch.Tensor) -> torch.Tensor:
    """Camera-frame rays (OpenCV axes: x right, y down, z forward) of an OpenCV fisheye lens.

    Args:
        xd, yd: [B] float, distorted normalised coordinates.
        distortion: [B, 6] float, k1, k2, k3, k4 (p1, p2 unused).

    Returns:
        [B, 3] unit rays: theta from Newton's method (:data:`UNDISTORT_ITERATIONS` steps from
        theta = r_d) on the equidistant model,

    .. math::
        r_d = \\theta (1 + k_1 \\theta^2 + k_2 \\theta^4 + k_3 \\theta^6 + k_4 \\theta^8),\\quad
        r_d = \\lVert (x_d, y_d) \\rVert,\\quad
        \\mathrm{ray} = (\\sin\\theta\\, x_d / r_d,\\; \\sin\\theta\\, y_d / r_d,\\; \\cos\\theta).
    """
    k1, k2, k3, k4 = distortion[:, :4].unbind(-1)
    rd = torch.sqrt(xd * xd + yd * yd)
    theta = rd
    for _ in range(UNDISTORT_ITERATIONS):
        t2 = theta * theta
        f = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - rd
        df = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
        df = torch.where(df.abs() < 1e-12, torch.full_like(df, 1e-12), df)
        theta = theta - f / df
    s = torch.where(rd > 1e-12, torch.sin(theta) / rd.clamp_min(1e-12), torch.ones_like(rd))
    return torch.stack([xd * s, yd * s, torch.cos(theta)], dim=-1)


def generate_rays(
    c2w: torch.Tensor,
    intrinsics: torch.Tensor,
    distortion: torch.Tensor | None,
    px: torch.Tensor,
    py: torch.Tensor,
    fisheye: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """World-space rays through pixel centres.

    Args:
        c2w: [B, 3, 4] float32 (or float64) camera-to-world, OpenGL convention.
        intrinsics: [B, 4] float, fx, fy, cx, cy in pixels.
        distortion: [B, 6] float k1, k2, k3, k4, p1, p2, or None for an ideal pinhole (zeros
            give the same rays, after a few no-op Newton steps).
        px, py: [B] integer (or float) pixel column and row.
        fisheye: the lens is OpenCV's fisheye (``distortion`` required): the camera-frame ray
            is :func:`fisheye_ray` (x', y', z') and d = R (x', -y', -z') / |.| instead.

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
    _check_lens(distortion, (b, 6), fisheye, c2w)
    dtype = c2w.dtype
    intr = intrinsics.to(dtype)
    x = (px.to(dtype) + 0.5 - intr[:, 2]) / intr[:, 0]
    y = (py.to(dtype) + 0.5 - intr[:, 3]) / intr[:, 1]
    rot = c2w[:, :, :3]
    if fisheye:
        cam = fisheye_ray(x, y, distortion.to(dtype))
        d = rot[:, :, 0] * cam[:, None, 0] - rot[:, :, 1] * cam[:, None, 1] - rot[:, :, 2] * cam[:, None, 2]
        return c2w[:, :, 3].contiguous(), d / d.norm(dim=-1, keepdim=True)
    if distortion is not None:
        x, y = undistort(x, y, distortion.to(dtype))
    d = rot[:, :, 0] * x[:, None] - rot[:, :, 1] * y[:, None] - rot[:, :, 2]
    d = d / d.norm(dim=-1, keepdim=True)
    return c2w[:, :, 3].contiguous(), d


def view_rays(c2w: torch.Tensor, intrinsics: torch.Tensor, distortion: torch.Tensor | None, width: int, height: int,
              device: torch.device | str, fisheye: bool = False, shift: tuple[float, float] = (0.0, 0.0),
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """The rays of every pixel of one camera, row by row, in one launch: pixel (px, py) is
    sampled at (px + 1/2 + dx, py + 1/2 + dy) for ``shift`` = (dx, dy), as :func:`generate_rays`
    samples it at its pixel coordinates (px + dx, py + dy) (float32, same lens models).

    Args:
        c2w: [3, 4] camera-to-world; intrinsics: [4] fx, fy, cx, cy; distortion: [6] k1 k2 k3
            k4 p1 p2 or None (pinhole); ``fisheye`` as in :func:`generate_rays` (needs distortion).
        width, height: image size; device: where the rays go (the camera may be anywhere).

    Returns:
        rays_o, rays_d: [height·width, 3] float32 on ``device``, rays_d unit.
    """
    _check(c2w, "c2w", (3, 4))
    _check(intrinsics, "intrinsics", (4,))
    _check_lens(distortion, (6,), fisheye)
    lens = LENS_FISHEYE if fisheye else LENS_PINHOLE if distortion is None else LENS_OPENCV
    dist = torch.zeros(6, device=device) if distortion is None else distortion  # made where it is read
    n = width * height
    rays_o = torch.empty(n, 3, dtype=torch.float32, device=device)
    rays_d = torch.empty(n, 3, dtype=torch.float32, device=device)
    _wp.launch(K.view_rays, n, [width, float(shift[0]), float(shift[1]), lens,
                                c2w.to(device, torch.float32).reshape(-1).contiguous(),
                                intrinsics.to(device, torch.float32).reshape(1, 4).contiguous(),
                                dist.to(device, torch.float32).reshape(1, 6).contiguous(), rays_o, rays_d],
               _wp.device_of(rays_o))
    return rays_o, rays_d
