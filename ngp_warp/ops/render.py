"""``render_rays``: rays → pixels through an occupancy grid and any radiance field.

Ray marching (:func:`ngp_warp.ray_marching`, no gradient) produces packed samples, the field
is evaluated on them in torch, and compositing (:mod:`ngp_warp.ops.composite`) blends them front to
back with a hand-written backward, so gradients reach the field's parameters. Embed it in a
model::

    import torch, ngp_warp

    aabb = torch.tensor([-1.5, -1.5, -1.5, 1.5, 1.5, 1.5], device="cuda")
    grid = ngp_warp.OccupancyGrid(aabb, resolution=128).to("cuda")
    field = MyField().cuda()        # (positions [S,3], directions [S,3]) -> (sigmas [S], rgbs [S,3])
    opt = torch.optim.Adam(field.parameters(), lr=1e-2)
    step = grid.default_step_size   # box diagonal / 1024
    for it, (rays_o, rays_d, target) in enumerate(batches):  # [n,3], [n,3] unit, [n,3]
        grid.update(it, lambda x: field.density(x) * step)
        out = ngp_warp.render_rays(rays_o, rays_d, grid, field,
                                   ngp_warp.MarchOptions(step_size=step, stratified=True),
                                   background=torch.ones(3, device="cuda"))
        loss = torch.nn.functional.mse_loss(out["rgb"], target)
        opt.zero_grad(); loss.backward(); opt.step()
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import torch

from ngp_warp.ops.composite import composite, composite_packed, ray_offsets_from_indices
from ngp_warp.ops.occupancy import OccupancyGrid
from ngp_warp.ops.prune import prune_samples
from ngp_warp.ops.raymarch import MarchOptions, RaySamples, ray_marching

FieldFn = Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]


def _background(background, rays_o: torch.Tensor) -> torch.Tensor | None:
    """``background`` as a [3] or [N, 3] tensor for the N ``rays_o``, float64 on the float64
    path (which keeps its digits, and its gradient's), else float32."""
    if background is None:
        return None
    n_rays = rays_o.shape[0]
    dtype = torch.float64 if rays_o.dtype == torch.float64 else torch.float32
    bg = torch.as_tensor(background, dtype=dtype, device=rays_o.device)
    if bg.dim() == 0:
        bg = bg.expand(3)
    if tuple(bg.shape) not in ((3,), (n_rays, 3)):
        raise ValueError(f"background must be a float, [3] or [{n_rays}, 3], got shape {tuple(bg.shape)}")
    return bg


def _check_sigmas(sigmas, n: int, source: str) -> None:
    if not isinstance(sigmas, torch.Tensor) or sigmas.shape[0] != n or sigmas.numel() != n:
        raise ValueError(f"{source} must return sigmas of shape [{n}] or [{n}, 1], "
                         f"got {getattr(sigmas, 'shape', type(sigmas).__name__)}")


def _checked(fn: Callable, name: str) -> Callable:
    """``fn`` (a field or density function) that raises ValueError when the σ it returns (its
    first output) is negative or not finite; reading the check is one host sync."""
    def checked(*inputs):
        out = fn(*inputs)
        sigmas = out[0] if isinstance(out, tuple) else out
        if isinstance(sigmas, torch.Tensor) and sigmas.numel() and not bool((sigmas >= 0).all()):
            raise ValueError(f"{name} returned negative or NaN sigmas (densities must be ≥ 0, e.g. through "
                             f"softplus or exp)")
        return out

    return checked


def _select(samples: RaySamples, keep: torch.Tensor) -> RaySamples:
    """The samples where ``keep`` ([S] bool) holds, with their ray offsets (sizing them is a sync)."""
    ray_indices = samples.ray_indices[keep]
    n_rays = samples.ray_offsets.shape[0] - 1
    offsets = (ray_offsets_from_indices(ray_indices, n_rays) if ray_indices.numel()
               else torch.zeros(n_rays + 1, dtype=torch.int32, device=keep.device))
    return RaySamples(ray_indices, samples.t_starts[keep], samples.t_ends[keep], samples.positions[keep],
                      samples.directions[keep], offsets)


def _pruned(samples: RaySamples, sigma_fn, grid: OccupancyGrid, early_stop_eps: float,
            capacity: int | None, alpha_thre: float) -> tuple[RaySamples, dict]:
    """The samples that go to the field (those with α ≥ ``alpha_thre`` that composite), and
    render_rays's pruning outputs (``n_marched``, ``ray_mask``, ``n_contributing``)."""
    n_rays, dev = samples.ray_offsets.shape[0] - 1, samples.ray_offsets.device
    extra = {"n_marched": samples.n_samples}
    if samples.n_samples > 0:
        with torch.no_grad():
            sigmas = sigma_fn(samples.positions)
        _check_sigmas(sigmas, samples.n_samples, "sigma_fn")
        sigmas = sigmas.reshape(samples.n_samples).float()
        if alpha_thre > 0:
            keep = -torch.expm1(-sigmas * (samples.t_ends - samples.t_starts)) >= alpha_thre
            samples, sigmas = _select(samples, keep), sigmas[keep]
    if samples.n_samples > 0:
        centre = tuple(0.5 * (a + b) for a, b in zip(grid.aabb_host[:3], grid.aabb_host[3:]))
        pruned = prune_samples(samples, sigmas.contiguous(), early_stop_eps, capacity, centre)
        extra.update(ray_mask=pruned.ray_mask, n_contributing=pruned.n_contributing)
        return pruned.samples, extra
    extra.update(ray_mask=torch.ones(n_rays, dtype=torch.bool, device=dev),
                 n_contributing=torch.zeros(1, dtype=torch.int32, device=dev))
    return samples, extra


def _within(samples: RaySamples, t_min: torch.Tensor | None, t_max: torch.Tensor | None) -> RaySamples:
    """The samples whose midpoint lies in their ray's [t_min, t_max] ([N] each, None: unbounded)."""
    if (t_min is None and t_max is None) or samples.n_samples == 0:
        return samples
    mid, rays = _midpoints(samples), samples.ray_indices
    keep = torch.ones_like(mid, dtype=torch.bool)
    if t_min is not None:
        keep &= mid >= t_min[rays]
    if t_max is not None:
        keep &= mid <= t_max[rays]
    return _select(samples, keep)


def _midpoints(samples: RaySamples) -> torch.Tensor:
    """[S] float32 distance of each sample's midpoint along its ray (where the march put its position)."""
    return 0.5 * (samples.t_starts + samples.t_ends)


def _attached(samples: RaySamples, rays_o: torch.Tensor, rays_d: torch.Tensor) -> RaySamples:
    """``samples`` whose positions and directions carry the gradient to the rays that require it
    (camera refinement, :mod:`ngp_warp.training.camera_refinement`, or a model of one's own): the march's
    positions plus :math:`(o + t d) - \\mathrm{sg}(o + t d)` of each sample's ray at its midpoint
    :math:`t`, and its directions plus :math:`d - \\mathrm{sg}(d)` (both zero in value; padding
    rows, of ray N, get none), so that :math:`\\partial x / \\partial o = I`,
    :math:`\\partial x / \\partial d = t I` with the distances held fixed, and a view-dependent
    field's direction gradient reaches ``rays_d``. float64 rays give float64 positions
    :math:`o + t d` and directions :math:`d` outright (the float64 path)."""
    rays = torch.nn.functional.pad(torch.stack([rays_o, rays_d]), (0, 0, 0, 1))[:, samples.ray_indices]
    moved = rays[0] + _midpoints(samples)[:, None].to(rays.dtype) * rays[1]
    if rays.dtype == torch.float64:
        return dataclasses.replace(samples, positions=moved, directions=rays[1])
    return dataclasses.replace(samples, positions=samples.positions + (moved - moved.detach()),
                               directions=samples.directions + (rays[1] - rays[1].detach()))


class _ScaleGradient(torch.autograd.Function):
    """Identity forward; the backward multiplies the gradient by ``scale`` (broadcast)."""

    @staticmethod
    def forward(ctx, x, scale):
        ctx.save_for_backward(scale)
        return x.view_as(x)

    @staticmethod
    def backward(ctx, grad):
        (scale,) = ctx.saved_tensors
        return grad * scale, None


def _near_camera_scale(samples: RaySamples, distance: float) -> torch.Tensor:
    """[S] float32 ``min(1, (t / distance)²)`` at each sample's midpoint t: Philip and
    Deschaintre's "Floaters No More" (2023). A camera's near space, which few other views see,
    gets as much gradient per unit of its footprint as far space, and stops growing floaters
    that explain one image; the rendered values are unchanged."""
    return (_midpoints(samples) * (1.0 / distance)).square().clamp_max(1.0)


def _shade(samples: RaySamples, field_fn: FieldFn, early_stop_eps: float, ray_images: torch.Tensor | None,
           near_gradient_distance: float = 0.0):
    """(rgb [N, 3], opacity [N], depth [N], weights [S]) of the samples through ``field_fn``,
    which also gets each sample's image (padding rows, of ray N: image 0) given ``ray_images``;
    the field's outputs' gradients scaled near the ray origins given ``near_gradient_distance``."""
    n_rays, dev = samples.ray_offsets.shape[0] - 1, samples.ray_offsets.device
    n_samples = samples.n_samples
    if n_samples == 0 and not torch.is_grad_enabled():
        rgb, per_ray = torch.zeros(n_rays, 3, device=dev), torch.zeros(n_rays, device=dev)
        return rgb, per_ray, per_ray.clone(), torch.zeros(0, device=dev)
    if ray_images is None:  # with no sample at all, the field's zero rows keep the result in its graph
        sigmas, rgbs = field_fn(samples.positions, samples.directions)
    else:
        sample_images = torch.nn.functional.pad(ray_images, (0, 1))[samples.ray_indices]
        sigmas, rgbs = field_fn(samples.positions, samples.directions, sample_images)
    _check_sigmas(sigmas, n_samples, "field_fn")
    if not isinstance(rgbs, torch.Tensor) or tuple(rgbs.shape) != (n_samples, 3):
        raise ValueError(f"field_fn must return rgbs of shape [{n_samples}, 3], "
                         f"got {getattr(rgbs, 'shape', type(rgbs).__name__)}")
    if sigmas.dim() != 1:  # [S, 1]; a reshape of [S] would add a node to the backward
        sigmas = sigmas.reshape(n_samples)
    if near_gradient_distance > 0 and torch.is_grad_enabled():
        scale = _near_camera_scale(samples, near_gradient_distance)
        sigmas, rgbs = _ScaleGradient.apply(sigmas, scale), _ScaleGradient.apply(rgbs, scale[:, None])
    if n_samples == 0:  # zeros, in the field's graph
        zero = sigmas.sum() + rgbs.sum()
        rgb, per_ray = torch.zeros(n_rays, 3, device=dev, dtype=zero.dtype), torch.zeros(n_rays, device=dev, dtype=zero.dtype)
        return rgb + zero, per_ray + zero, per_ray + zero, sigmas * 0
    if sigmas.dtype == torch.float64:  # the public op's float64 path (the twin)
        f64 = torch.float64
        return composite(sigmas, rgbs.to(f64), samples.t_starts.to(f64), samples.t_ends.to(f64),
                         samples.ray_indices, n_rays, early_stop_eps, return_weights=True, validate=False)
    return composite_packed(sigmas.float().contiguous(), rgbs.float().contiguous(),
                            samples.t_starts, samples.t_ends, samples.ray_offsets, early_stop_eps)


def _flat_rays(rays_o, rays_d, sample_capacity) -> tuple[torch.Tensor, torch.Tensor, torch.Size]:
    """(rays_o [N, 3], rays_d [N, 3], their leading shape) from rays of any shape [..., 3] and
    strides, float32 or float64 (both alike); one-line ValueErrors otherwise."""
    for name, t in (("rays_o", rays_o), ("rays_d", rays_d)):
        if not isinstance(t, torch.Tensor) or t.dim() < 1 or t.shape[-1] != 3:
            raise ValueError(f"{name} must be a [..., 3] tensor, got {getattr(t, 'shape', type(t).__name__)}")
        if t.dtype not in (torch.float32, torch.float64) or t.dtype != rays_o.dtype:
            raise ValueError(f"rays_o and rays_d must both be float32 (or both float64, the float64 path), "
                             f"got {rays_o.dtype} and {rays_d.dtype}")
    if rays_o.shape != rays_d.shape:
        raise ValueError(f"rays_o has shape {list(rays_o.shape)} but rays_d {list(rays_d.shape)}")
    if rays_o.dtype == torch.float64 and sample_capacity is not None:
        raise ValueError("sample_capacity is for float32 rays (the float64 path sizes its samples)")
    return rays_o.reshape(-1, 3), rays_d.reshape(-1, 3), rays_o.shape[:-1]


def _ray_interval(t_min, t_max, leading: torch.Size, device, sample_capacity, alpha_thre, sigma_fn):
    """render_rays' nerfacc-style options checked: ``t_min``/``t_max`` flattened to [N] (or
    None); one-line ValueErrors."""
    if not 0.0 <= alpha_thre < 1.0:
        raise ValueError(f"alpha_thre must be in [0, 1), got {alpha_thre!r}")
    if alpha_thre > 0 and sigma_fn is None:
        raise ValueError("alpha_thre needs a sigma_fn (the densities it thresholds)")
    given = [t for t in (t_min, t_max) if t is not None]
    if (given or alpha_thre > 0) and sample_capacity is not None:
        raise ValueError("t_min, t_max and alpha_thre select samples after the march, which a fixed "
                         "sample_capacity cannot take")
    for name, t in (("t_min", t_min), ("t_max", t_max)):
        if t is not None and (not isinstance(t, torch.Tensor) or t.shape != leading or t.device != device
                              or not t.is_floating_point()):
            raise ValueError(f"{name} must be a float tensor of shape {list(leading)} on {device}, "
                             f"got {getattr(t, 'shape', type(t).__name__)}")
    return tuple(None if t is None else t.reshape(-1) for t in (t_min, t_max))


def _check_render_settings(rays_o, early_stop_eps, sigma_fn, sample_capacity, ray_images,
                           near_gradient_distance) -> None:
    """render_rays' own arguments (the march checks the rays): one-line ValueErrors."""
    if early_stop_eps < 0:
        raise ValueError(f"early_stop_eps must be ≥ 0, got {early_stop_eps}")
    if not near_gradient_distance >= 0:
        raise ValueError(f"near_gradient_distance must be ≥ 0, got {near_gradient_distance}")
    if sample_capacity is not None and (sigma_fn is None or sample_capacity < 1):
        raise ValueError("sample_capacity needs a sigma_fn and must be ≥ 1")
    n_rays = rays_o.shape[0]
    if ray_images is not None and (not isinstance(ray_images, torch.Tensor) or ray_images.dtype != torch.int64
                                   or tuple(ray_images.shape) != (n_rays,) or ray_images.device != rays_o.device):
        raise ValueError(f"ray_images must be None or a [{n_rays}] int64 tensor on {rays_o.device}, "
                         f"got {getattr(ray_images, 'shape', type(ray_images).__name__)}")


def render_rays(
    rays_o: torch.Tensor, rays_d: torch.Tensor, grid: OccupancyGrid, field_fn: FieldFn,
    march: MarchOptions = MarchOptions(), *, early_stop_eps: float = 1e-4, background=None,
    sigma_fn: Callable[[torch.Tensor], torch.Tensor] | None = None, sample_capacity: int | None = None,
    return_samples: bool = False, before_sync: Callable[[], None] | None = None,
    ray_images: torch.Tensor | None = None, validate: bool = True, near_gradient_distance: float = 0.0,
    alpha_thre: float = 0.0, t_min: torch.Tensor | None = None, t_max: torch.Tensor | None = None,
    normalize_depth: bool = False,
) -> dict:
    """Render rays through ``grid`` with the radiance field ``field_fn`` (:math:`w_i` as in
    :func:`ngp_warp.composite`):

    .. math::

        C_{out} = \\sum_i w_i c_i + b\\,(1 - O), \\qquad O = \\sum_i w_i, \\qquad
        D = \\sum_i w_i \\frac{t^{start}_i + t^{end}_i}{2}

    Args:
        rays_o, rays_d: [N, 3] float32 origins and unit directions, any strides; leading
            dimensions [..., 3] are flattened (the outputs per ray take them back). Rays that
            require grad get it through the sample positions and directions (:func:`_attached`).
            float64 rays (and field) march in float32, then position, shade and composite in
            float64 through the pure-torch twin, differentiable to any order (``gradcheck``).
        grid: :class:`ngp_warp.OccupancyGrid` on the rays' device.
        field_fn: ``(positions [S, 3] float32, directions [S, 3] float32) → (sigmas [S] or
            [S, 1] ≥ 0, rgbs [S, 3])``. With no sample at all it is called with S = 0 under
            autograd (the zero outputs stay in its graph: ``backward`` runs), else not at all.
        march: the ray interval, steps and caps (:class:`ngp_warp.MarchOptions`; ``step_size``
            defaults to the box diagonal / 1024).
        early_stop_eps: samples behind transmittance ``< early_stop_eps`` contribute nothing
            (``field_fn`` still runs on them unless ``sigma_fn`` prunes them first).
        background: None, a float, [3] or [N, 3] colour blended behind the samples.
        sigma_fn: ``positions [S, 3] → σ [S]``; when given, it is evaluated without gradient on
            every marched sample and only the samples that composite (transmittance in front
            ``≥ early_stop_eps``) go to ``field_fn`` (see :func:`ngp_warp.prune_samples`).
        sample_capacity: with ``sigma_fn``, ``field_fn`` gets exactly this many rows when any
            sample was marched (padding at the grid's centre, zero weight): fixed shapes; rays
            that do not fit are dropped and flagged in ``ray_mask``.
        return_samples: also return the packed samples and their differentiable weights.
        before_sync: as in :func:`ngp_warp.ray_marching`: called once the march has queued its
            count, before the host waits for it (device work queued there hides the wait).
        ray_images: [N] int64 training image of each ray (per-image appearance codes), or
            None; then ``field_fn(positions, directions, images [S] int64)`` (padding: image 0).
        validate: check finite unit rays (read with the march's count: no extra sync) and σ ≥ 0
            from ``field_fn`` and ``sigma_fn`` (a sync each), else ValueError; False skips it.
        near_gradient_distance: > 0: each sample's σ and colour gradients are scaled by
            :math:`\\min(1, (t / \\text{this})^2)` (:func:`_near_camera_scale`).
        alpha_thre: with ``sigma_fn``, samples whose α = 1 − exp(−σ δ) is below this are left
            out before the field (nerfacc's ``alpha_thre``).
        t_min, t_max: [N] float32 per-ray interval (nerfacc's): samples whose midpoint lies
            outside it are left out (the march's ``near``/``far`` must cover it).
        normalize_depth: depth as the expected distance Σ w t / Σ w, not Σ w t.

    Returns:
        dict with ``rgb`` [N, 3], ``opacity`` [N], ``depth`` [N] (float32, differentiable w.r.t.
        the field) and ``n_samples`` (int, rows given to ``field_fn``); with ``sigma_fn`` also
        ``n_marched`` (int), ``n_contributing`` ([1] int32 on the device) and ``ray_mask``
        ([N] bool, False for dropped rays, which render as background); with
        ``return_samples`` also ``weights`` [S], ``ray_indices`` [S] int64, ``t_starts`` [S],
        ``t_ends`` [S] and ``ray_offsets`` [N + 1] int32 (samples of ray r are
        ``ray_offsets[r] : ray_offsets[r+1]``; padding rows lie past ``ray_offsets[N]``).
    """
    rays_o, rays_d, leading = _flat_rays(rays_o, rays_d, sample_capacity)
    if isinstance(ray_images, torch.Tensor) and ray_images.shape == leading:
        ray_images = ray_images.reshape(-1)
    _check_render_settings(rays_o, early_stop_eps, sigma_fn, sample_capacity, ray_images, near_gradient_distance)
    t_min, t_max = _ray_interval(t_min, t_max, leading, rays_o.device, sample_capacity, alpha_thre, sigma_fn)
    samples = ray_marching(rays_o.float(), rays_d.float(), grid, march, before_sync=before_sync, validate=validate,
                           unit_directions=True)
    if validate:
        field_fn, sigma_fn = _checked(field_fn, "field_fn"), sigma_fn and _checked(sigma_fn, "sigma_fn")
    bg = _background(background, rays_o)
    samples, extra = _within(samples, t_min, t_max), {}
    if sigma_fn is not None:
        samples, extra = _pruned(samples, sigma_fn, grid, early_stop_eps, sample_capacity, alpha_thre)
    if rays_o.dtype == torch.float64 or ((rays_o.requires_grad or rays_d.requires_grad) and torch.is_grad_enabled()):
        samples = _attached(samples, rays_o, rays_d)
    shaded = _shade(samples, field_fn, early_stop_eps, ray_images, near_gradient_distance)
    return _outputs(*shaded, samples, bg, leading, extra, normalize_depth, return_samples)


def _outputs(rgb: torch.Tensor, opacity: torch.Tensor, depth: torch.Tensor, weights: torch.Tensor,
             samples: RaySamples, bg: torch.Tensor | None, leading: torch.Size, extra: dict,
             normalize_depth: bool, return_samples: bool) -> dict:
    """:func:`render_rays`'s dict from the composite of its N rays (rgb [N, 3], opacity and
    depth [N], weights [S] of the S ``samples``): ``bg`` ([3] or [N, 3], None: none) blended
    behind, the per-ray outputs shaped ``leading``, ``extra`` (the pruning's outputs) added."""
    if bg is not None:
        rgb = rgb + bg * (1.0 - opacity)[:, None]
    if normalize_depth:
        depth = depth / opacity.clamp_min(1e-10)
    out = {"rgb": rgb.reshape(*leading, 3), "opacity": opacity.reshape(leading), "depth": depth.reshape(leading),
           "n_samples": samples.n_samples, **extra}
    if "ray_mask" in out:
        out["ray_mask"] = out["ray_mask"].reshape(leading)
    if return_samples:
        out.update(weights=weights, ray_indices=samples.ray_indices, t_starts=samples.t_starts,
                   t_ends=samples.t_ends, ray_offsets=samples.ray_offsets)
    return out
