"""The photometric loss of rendered rays over their backgrounds (a Warp forward that reduces
over the pixels, and a hand-written backward)."""

from __future__ import annotations

import torch

from ngp_warp import _wp
from ngp_warp.ops._differentiable_once import refuse_second_derivative
from ngp_warp.kernels import ray_loss as K


class _RayLoss(torch.autograd.Function):
    """The Warp forward and hand-written backward of :func:`ray_loss`."""

    @staticmethod
    def forward(ctx, rgb, opacity, target, background, ray_mask, extra, extra_weight: float, delta: float, k: int):
        n_pixels, device = target.shape[0], _wp.device_of(rgb)
        mask = None if ray_mask is None else ray_mask.view(torch.uint8)
        sums = torch.zeros(4, dtype=torch.float32, device=rgb.device)
        loss = torch.empty((), dtype=torch.float32, device=rgb.device)
        mse = torch.empty((), dtype=torch.float32, device=rgb.device)
        items = -(-n_pixels // K.RAYS_PER_THREAD)
        _wp.launch(K.ray_loss_sums, items,
                   [n_pixels, k, items, rgb, opacity, background, target, int(mask is not None), mask,
                    int(extra is not None), extra, delta, sums],
                   device, align=items)  # one CPU thread: the sums are atomics
        _wp.launch(K.ray_loss_finish, 1, [extra_weight, sums, loss.view(1), mse.view(1)], device)
        ctx.save_for_backward(rgb, opacity, target, background, mask, sums)
        ctx.extra_weight, ctx.delta, ctx.has_extra, ctx.k = extra_weight, delta, extra is not None, k
        ctx.mark_non_differentiable(mse)
        ctx.set_materialize_grads(False)  # no zeros for mse's gradient, which is never used
        return loss, mse

    @staticmethod
    def backward(ctx, grad_loss, _grad_mse):
        if grad_loss is None:
            return None, None, None, None, None, None, None, None, None
        rgb, opacity, target, background, mask, sums = ctx.saved_tensors
        grad_rgb, grad_opacity = torch.empty_like(rgb), torch.empty_like(opacity)
        grad_extra = torch.empty_like(opacity) if ctx.has_extra else None
        _wp.launch(K.ray_loss_backward, rgb.shape[0],
                   [ctx.k, rgb, opacity, background, target, int(mask is not None), mask, int(ctx.has_extra),
                    ctx.delta, ctx.extra_weight, sums, grad_loss.detach().float().reshape(1), grad_rgb, grad_opacity,
                    grad_extra],
                   _wp.device_of(rgb))
        grad_background = None
        if ctx.needs_input_grad[3]:  # c_p = mean_k(c_r + (1 - a_r) b_p): dL/db_p = sum_k (1 - a_r) dL/dc_r
            grad_background = ((1.0 - opacity.detach())[:, None] * grad_rgb).view(-1, ctx.k, 3).sum(1)
        grads = refuse_second_derivative("ray_loss", (grad_rgb, grad_opacity, grad_background, grad_extra),
                                         (rgb, opacity, background, grad_loss))
        return grads[0], grads[1], None, grads[2], None, grads[3], None, None, None


def ray_loss(rgb: torch.Tensor, opacity: torch.Tensor, target: torch.Tensor, background: torch.Tensor,
             ray_mask: torch.Tensor | None = None, extra: torch.Tensor | None = None, extra_weight: float = 0.0,
             huber_delta: float | None = None, rays_per_pixel: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """The photometric loss of rays rendered without a background (``render_rays(...,
    background=None)``), blended over ``background`` here, with an optional per-ray term,
    averaged over the pixels that ``ray_mask`` keeps, in one launch forward and one backward.
    A pixel p is the mean of its ``rays_per_pixel`` = K rays (rows pK ... pK + K − 1; K = 1:
    one ray per pixel), e.g. the sub-pixel rays of :func:`ngp_warp.ops.batch.sample_pixels`.

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
        background: [N / K, 3] float32 per-pixel background :math:`b_p` (differentiable: a
            learned background, e.g. :meth:`ngp_warp.ops.field.NGPField.background`).
        ray_mask: optional [N] bool :math:`m_r` (e.g. ``render_rays``'s ``ray_mask``); None: all.
        extra: optional [N] float32 per-ray term :math:`x_r` (differentiable), e.g. the
            :func:`ngp_warp.ops.distortion.distortion_loss_packed` of the rays, weighted by
            ``extra_weight`` :math:`\\lambda`.
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
    if target.requires_grad:
        raise ValueError("ray_loss gives target no gradient; pass it detached (or use a torch loss)")
    if huber_delta is not None and not (isinstance(huber_delta, (int, float)) and huber_delta > 0):
        raise ValueError(f"huber_delta must be a number > 0 or None, got {huber_delta!r}")
    if not (isinstance(extra_weight, (int, float)) and extra_weight >= 0):
        raise ValueError(f"extra_weight must be a number ≥ 0, got {extra_weight!r}")
    return _RayLoss.apply(rgb.contiguous(), opacity.contiguous(), target.contiguous(), background.contiguous(),
                          None if ray_mask is None else ray_mask.contiguous(),
                          None if extra is None else extra.contiguous(), float(extra_weight),
                          0.0 if huber_delta is None else float(huber_delta), rays_per_pixel)
