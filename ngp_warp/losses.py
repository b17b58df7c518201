"""Losses: regularisers on packed samples (as ``render_rays(..., return_samples=True)`` returns
them) and the photometric loss of rendered rays."""

from __future__ import annotations

import torch

from ngp_warp import _wp
from ngp_warp.kernels import distortion as K
from ngp_warp.kernels import loss as L

_BLOCK = 32  # one thread per ray, as in ngp_warp.render


class _Distortion(torch.autograd.Function):
    """The Warp forward and hand-written backward of :func:`distortion_loss`."""

    @staticmethod
    def forward(ctx, weights, t_starts, t_ends, offsets):
        n_rays = offsets.shape[0] - 1
        loss = torch.empty(n_rays, dtype=torch.float32, device=weights.device)
        _wp.launch(K.distortion_forward, n_rays, [weights, t_starts, t_ends, offsets, loss],
                   _wp.device_of(weights), block_dim=_BLOCK)
        ctx.save_for_backward(weights, t_starts, t_ends, offsets)
        return loss

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_loss):
        weights, t_starts, t_ends, offsets = ctx.saved_tensors
        grad = torch.zeros_like(weights)  # rows of no ray (padding) get none
        _wp.launch(K.distortion_backward, offsets.shape[0] - 1,
                   [weights, t_starts, t_ends, offsets, grad_loss.float().contiguous(), grad],
                   _wp.device_of(weights), block_dim=_BLOCK)
        return grad, None, None, None


def distortion_loss_packed(weights: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor,
                           ray_offsets: torch.Tensor) -> torch.Tensor:
    """:func:`distortion_loss` on validated, contiguous float32 samples given by ``ray_offsets``
    [n_rays + 1] int32 (as ``render_rays(..., return_samples=True)`` returns them), skipping the
    search for each ray's first sample. Returns [n_rays] float32."""
    return _Distortion.apply(weights, t_starts, t_ends, ray_offsets)


def distortion_loss(weights: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor,
                    ray_indices: torch.Tensor, n_rays: int) -> torch.Tensor:
    """Mip-NeRF 360's distortion loss of every ray: small when a ray's weight sits in one
    short stretch (a crisp surface), large when it is spread along the ray.

    .. math::
        L_r = \\sum_{i,j} w_i w_j \\left|m_i - m_j\\right| + \\tfrac13 \\sum_i w_i^2 \\delta_i,
        \\qquad m_i = \\tfrac12 (t^{start}_i + t^{end}_i), \\quad \\delta_i = t^{end}_i - t^{start}_i

    (in the units of ``t``), computed in O(samples) with prefix sums.

    Args:
        weights: [S] float32 compositing weights :math:`w_i` (differentiable, e.g. from
            :func:`ngp_warp.composite` with ``return_weights``).
        t_starts, t_ends: [S] float32 sample intervals (no gradient).
        ray_indices: [S] int64 ray of each sample, **sorted** (samples of a ray contiguous and
            front to back; not checked on the device). Rows with index ``n_rays`` or more
            (the padding rows of ``render_rays``) belong to no ray and are ignored.
        n_rays: number of rays.

    Returns:
        [n_rays] float32 loss per ray (0 for rays without samples), differentiable w.r.t. ``weights``.
    """
    if not isinstance(weights, torch.Tensor) or weights.dim() != 1:
        raise ValueError(f"weights must be a [S] tensor, got {getattr(weights, 'shape', type(weights).__name__)}")
    n = weights.shape[0]
    for name, t in (("weights", weights), ("t_starts", t_starts), ("t_ends", t_ends)):
        if not isinstance(t, torch.Tensor) or tuple(t.shape) != (n,) or t.dtype != torch.float32:
            raise ValueError(f"{name} must be [{n}] float32, got {getattr(t, 'shape', t)} "
                             f"{getattr(t, 'dtype', '')}".rstrip())
        if t.device != weights.device:
            raise ValueError(f"{name} is on {t.device} but weights on {weights.device}")
    if (not isinstance(ray_indices, torch.Tensor) or tuple(ray_indices.shape) != (n,)
            or ray_indices.dtype != torch.int64 or ray_indices.device != weights.device):
        raise ValueError(f"ray_indices must be [{n}] int64 on {weights.device}")
    if not isinstance(n_rays, int) or n_rays < 0:
        raise ValueError(f"n_rays must be a non-negative int, got {n_rays!r}")
    _wp.device_of(weights)
    # offsets[r] = first sample of ray r (binary search: rows past the last ray are left out)
    offsets = torch.searchsorted(ray_indices, torch.arange(n_rays + 1, device=weights.device), out_int32=True)
    return distortion_loss_packed(weights.contiguous(), t_starts.contiguous(), t_ends.contiguous(), offsets)


class _RayLoss(torch.autograd.Function):
    """The Warp forward and hand-written backward of :func:`ray_loss`."""

    @staticmethod
    def forward(ctx, rgb, opacity, target, background, ray_mask, extra, extra_weight: float, delta: float, k: int):
        n_pixels, device = target.shape[0], _wp.device_of(rgb)
        mask = None if ray_mask is None else ray_mask.view(torch.uint8)
        sums = torch.zeros(4, dtype=torch.float32, device=rgb.device)
        loss = torch.empty((), dtype=torch.float32, device=rgb.device)
        mse = torch.empty((), dtype=torch.float32, device=rgb.device)
        items = -(-n_pixels // L.RAYS_PER_THREAD)
        _wp.launch(L.ray_loss_sums, items,
                   [n_pixels, k, items, rgb, opacity, background, target, int(mask is not None), mask,
                    int(extra is not None), extra, delta, sums],
                   device, align=items)  # one CPU thread: the sums are atomics
        _wp.launch(L.ray_loss_finish, 1, [extra_weight, sums, loss.view(1), mse.view(1)], device)
        ctx.save_for_backward(rgb, opacity, target, background, mask, sums)
        ctx.extra_weight, ctx.delta, ctx.has_extra, ctx.k = extra_weight, delta, extra is not None, k
        ctx.mark_non_differentiable(mse)
        ctx.set_materialize_grads(False)  # no zeros for mse's gradient, which is never used
        return loss, mse

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_loss, _grad_mse):
        if grad_loss is None:
            return None, None, None, None, None, None, None, None, None
        rgb, opacity, target, background, mask, sums = ctx.saved_tensors
        grad_rgb, grad_opacity = torch.empty_like(rgb), torch.empty_like(opacity)
        grad_extra = torch.empty_like(opacity) if ctx.has_extra else None
        _wp.launch(L.ray_loss_backward, rgb.shape[0],
                   [ctx.k, rgb, opacity, background, target, int(mask is not None), mask, int(ctx.has_extra),
                    ctx.delta, ctx.extra_weight, sums, grad_loss.float().reshape(1), grad_rgb, grad_opacity,
                    grad_extra],
                   _wp.device_of(rgb))
        return grad_rgb, grad_opacity, None, None, None, grad_extra, None, None, None


def ray_loss(rgb: torch.Tensor, opacity: torch.Tensor, target: torch.Tensor, background: torch.Tensor,
             ray_mask: torch.Tensor | None = None, extra: torch.Tensor | None = None, extra_weight: float = 0.0,
             huber_delta: float | None = None, rays_per_pixel: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """The photometric loss of rays rendered without a background (``render_rays(...,
    background=None)``), blended over ``background`` here, with an optional per-ray term,
    averaged over the pixels that ``ray_mask`` keeps, in one launch forward and one backward.
    A pixel p is the mean of its ``rays_per_pixel`` = K rays (rows pK ... pK + K − 1; K = 1:
    one ray per pixel), e.g. the sub-pixel rays of :func:`ngp_warp.batch.sample_pixels`.

    .. math::

        c_p = \\tfrac1K \\sum_{r \\in p} c_r, \\quad O_p = \\tfrac1K \\sum_{r \\in p} O_r, \\quad
        x_p = \\tfrac1K \\sum_{r \\in p} x_r, \\quad m_p = \\min_{r \\in p} m_r, \\quad
        e_p = c_p + b_p (1 - O_p) - \\hat c_p,

        \\mathrm{loss} = \\frac{\\sum_p m_p \\left(\\tfrac13 \\sum_k \\ell(e_{pk}) + \\lambda x_p\\right)}
                              {\\max(1, \\sum_p m_p)}, \\qquad
        \\mathrm{mse} = \\frac{\\sum_p m_p \\tfrac13 \\lVert e_p \\rVert^2}{\\max(1, \\sum_p m_p)}

    with :math:`\\ell(e) = e^2`, or Huber's :math:`\\tfrac12 e^2` for :math:`|e| < \\delta` and
    :math:`\\delta (|e| - \\delta / 2)` beyond.

    Args:
        rgb: [N, 3] float32 colour without background :math:`c_r` (differentiable).
        opacity: [N] float32 :math:`O_r` (differentiable).
        target: [N / K, 3] float32 pixel colours :math:`\\hat c_p`, already over ``background``
            (no gradient).
        background: [N / K, 3] float32 per-pixel background :math:`b_p` (no gradient).
        ray_mask: optional [N] bool :math:`m_r` (e.g. ``render_rays``'s ``ray_mask``); None: all.
        extra: optional [N] float32 per-ray term :math:`x_r` (differentiable), e.g. the
            :func:`distortion_loss_packed` of the rays, weighted by ``extra_weight`` :math:`\\lambda`.
        huber_delta: None for the squared error, else Huber's :math:`\\delta > 0`.
        rays_per_pixel: K ≥ 1, dividing N.

    Returns:
        (loss, mse): 0-dim float32 tensors on the rays' device; only ``loss`` has a gradient.
    """
    if not isinstance(rgb, torch.Tensor) or rgb.dim() != 2 or rgb.shape[1] != 3:
        raise ValueError(f"rgb must be [N, 3], got {getattr(rgb, 'shape', type(rgb).__name__)}")
    n, dev = rgb.shape[0], rgb.device
    if not (type(rays_per_pixel) is int and rays_per_pixel >= 1 and n % rays_per_pixel == 0):
        raise ValueError(f"rays_per_pixel must be an integer ≥ 1 dividing the {n} rays, got {rays_per_pixel!r}")
    pixels = n // rays_per_pixel
    expected = {"rgb": (rgb, (n, 3), torch.float32), "opacity": (opacity, (n,), torch.float32),
                "target": (target, (pixels, 3), torch.float32),
                "background": (background, (pixels, 3), torch.float32)}
    if ray_mask is not None:
        expected["ray_mask"] = (ray_mask, (n,), torch.bool)
    if extra is not None:
        expected["extra"] = (extra, (n,), torch.float32)
    for name, (t, shape, dtype) in expected.items():
        if not isinstance(t, torch.Tensor) or tuple(t.shape) != shape or t.dtype != dtype or t.device != dev:
            raise ValueError(f"{name} must be {list(shape)} {dtype} on {dev}, got "
                             f"{getattr(t, 'shape', type(t).__name__)} {getattr(t, 'dtype', '')}".rstrip())
    for name, t in (("target", target), ("background", background)):
        if t.requires_grad:
            raise ValueError(f"ray_loss gives {name} no gradient; pass it detached (or use a torch loss)")
    if huber_delta is not None and not (isinstance(huber_delta, (int, float)) and huber_delta > 0):
        raise ValueError(f"huber_delta must be a number > 0 or None, got {huber_delta!r}")
    if not (isinstance(extra_weight, (int, float)) and extra_weight >= 0):
        raise ValueError(f"extra_weight must be a number ≥ 0, got {extra_weight!r}")
    return _RayLoss.apply(rgb.contiguous(), opacity.contiguous(), target.contiguous(), background.contiguous(),
                          None if ray_mask is None else ray_mask.contiguous(),
                          None if extra is None else extra.contiguous(), float(extra_weight),
                          0.0 if huber_delta is None else float(huber_delta), rays_per_pixel)
