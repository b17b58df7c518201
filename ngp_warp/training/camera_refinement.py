"""Camera refinement: a learned pose correction per training image (instant-ngp's "optimize
extrinsics", nerfstudio's camera optimizer), for captures whose poses are a little off.

Image i's correction is a rotation :math:`R(\\omega_i)` about its camera centre and a
translation :math:`\\tau_i`, both in world coordinates (zero at the start), so that its rays are

.. math::

    o' = o + \\tau_i, \\qquad d' = R(\\omega_i)\\, d, \\qquad
    R(\\omega) = I + \\frac{\\sin\\theta}{\\theta} K + \\frac{1 - \\cos\\theta}{\\theta^2} K^2,
    \\quad \\theta = \\lVert\\omega\\rVert, \\; K = [\\omega]_\\times

(Rodrigues), i.e. camera-to-world :math:`[R(\\omega_i) R_i \\mid t_i + \\tau_i]`. Gradients reach
:math:`\\omega, \\tau` through the sample positions :math:`o' + t d'` (the march's distances
:math:`t` held fixed; :func:`ngp_warp.render_rays` attaches the positions to rays that require
grad), not through the view directions. Fitted by Adam with an L2 pull towards zero (instant-ngp's
1e-4), which keeps the corrections small where the images say nothing.

Measured on fox (H200, 60 s, RESULTS.md): it does not pay there. Its poses are good
to a fraction of a pixel, refining costs about 75 % more time per step (the hash grid's
position gradient), and at instant-ngp's learning rate of 1e-3 the corrections drift (mean 0.4°,
largest 3.1°: 25.4 dB); at the default 1e-4 they stay at 0.06° (30.4 dB, against about 31 dB
without). A capture whose poses are visibly off is where it is meant to help; held-out views of
a refined run are evaluated with their pose fitted as well (:mod:`ngp_warp.outputs.evaluate`).
"""

from __future__ import annotations

import torch

from ngp_warp.ops.optim import Adam

L2_PULL = 1e-4  # instant-ngp's extrinsic_l2_reg


def rotation_matrices(omega: torch.Tensor) -> torch.Tensor:
    """Rodrigues' rotation matrices (module docstring): omega [N, 3] axis-angle (radians) →
    [N, 3, 3], same dtype (under autocast too), differentiable (at zero as well: θ is taken as
    √(|ω|² + 1e-24))."""
    if omega.ndim != 2 or omega.shape[1] != 3:
        raise ValueError(f"omega must be [N, 3], got {tuple(omega.shape)}")
    theta = (omega.square().sum(-1) + 1e-24).sqrt()[:, None, None]
    zero = torch.zeros_like(omega[:, 0])
    wx, wy, wz = omega.unbind(-1)
    k = torch.stack([zero, -wz, wy, wz, zero, -wx, -wy, wx, zero], dim=-1).reshape(-1, 3, 3)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device)
    with torch.autocast(omega.device.type, enabled=False):  # K² in omega's dtype, not autocast's
        k2 = k @ k
    return eye + torch.sin(theta) / theta * k + (1.0 - torch.cos(theta)) / theta.square() * k2


class CameraRefinement(torch.nn.Module):
    """Pose corrections of ``n_images`` training images (module docstring).

    Attributes:
        omega: [n_images, 3] float32 rotation (axis-angle, world frame, about the camera centre).
        tau: [n_images, 3] float32 translation (world units).
    """

    def __init__(self, n_images: int, device: torch.device | str = "cpu"):
        super().__init__()
        if type(n_images) is not int or n_images < 1:
            raise ValueError(f"n_images must be an int ≥ 1, got {n_images!r}")
        self.omega = torch.nn.Parameter(torch.zeros(n_images, 3, device=device))
        self.tau = torch.nn.Parameter(torch.zeros(n_images, 3, device=device))

    def rays(self, image_indices: torch.Tensor, rays_o: torch.Tensor,
             rays_d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Corrected rays: image_indices [N] int64, rays_o and unit rays_d [N, 3] float32 →
        (o + τ, R(ω) d) [N, 3] float32, differentiable w.r.t. ω and τ (d' stays unit). Elementwise
        products rather than a matmul, so that the rays stay float32 under autocast."""
        rotations = rotation_matrices(self.omega)[image_indices]
        return rays_o + self.tau[image_indices], (rotations * rays_d[:, None, :]).sum(-1)

    @torch.no_grad()
    def refined_c2w(self, c2w: torch.Tensor) -> torch.Tensor:
        """The corrected camera-to-world matrices: c2w [n_images, 3, 4] → [R(ω) R | t + τ]
        [n_images, 3, 4], float32 on the corrections' device."""
        c2w = c2w.to(self.omega.device, torch.float32)
        if tuple(c2w.shape) != (self.omega.shape[0], 3, 4):
            raise ValueError(f"c2w must be [{self.omega.shape[0]}, 3, 4], got {tuple(c2w.shape)}")
        rotations = rotation_matrices(self.omega)
        return torch.cat([rotations @ c2w[:, :, :3], (c2w[:, :, 3] + self.tau)[:, :, None]], dim=-1)

    def optimizer(self, lr: float) -> Adam:
        """Adam over ω and τ with learning rate ``lr`` and the L2 pull :data:`L2_PULL`."""
        return Adam([self.omega, self.tau], lr=lr, weight_decay=L2_PULL, eps=1e-15)

    @torch.no_grad()
    def summary(self) -> str:
        """The mean and largest rotation (degrees) and shift (world units), in words."""
        angles, shifts = self.omega.norm(dim=-1).rad2deg(), self.tau.norm(dim=-1)
        return (f"rotations {float(angles.mean()):.3f}° mean, {float(angles.max()):.3f}° largest; "
                f"shifts {float(shifts.mean()):.4f} mean, {float(shifts.max()):.4f} largest")
