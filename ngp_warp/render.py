"""``render_rays``: rays → pixels through an occupancy grid and any radiance field.

Ray marching (:func:`ngp_warp.ray_marching`, no gradient) produces packed samples, the field
is evaluated on them in torch, and the compositing autograd function defined here (behind
:func:`ngp_warp.composite`) blends them front to back with a hand-written backward, so
gradients reach the field's parameters. Embed it in a model::

    import torch, ngp_warp

    aabb = torch.tensor([-1.5, -1.5, -1.5, 1.5, 1.5, 1.5], device="cuda")
    grid = ngp_warp.OccupancyGrid(aabb, resolution=128).to("cuda")
    field = MyField().cuda()        # (positions [S,3], directions [S,3]) -> (sigmas [S], rgbs [S,3])
    opt = torch.optim.Adam(field.parameters(), lr=1e-2)
    step = grid.default_step_size   # box diagonal / 1024
    for it, (rays_o, rays_d, target) in enumerate(batches):  # [n,3], [n,3] unit, [n,3]
        grid.update(it, lambda x: field.density(x) * step)
        out = ngp_warp.render_rays(rays_o, rays_d, grid, field, step_size=step,
                                   background=torch.ones(3, device="cuda"), stratified=True)
        loss = torch.nn.functional.mse_loss(out["rgb"], target)
        opt.zero_grad(); loss.backward(); opt.step()
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from ngp_warp import _wp
from ngp_warp.kernels import composite as K
from ngp_warp.occupancy import OccupancyGrid
from ngp_warp.prune import PrunedSamples, prune_samples
from ngp_warp.raymarch import ray_marching

FieldFn = Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]

# CUDA block size of this module's kernels: one thread walks a whole ray, and a batch has ~10^4
# rays, so small blocks spread them over all multiprocessors.
_BLOCK = 32


class _Composite(torch.autograd.Function):
    """Compositing with the Warp forward and hand-written backward kernels."""

    @staticmethod
    def forward(ctx, sigmas, rgbs, t_starts, t_ends, ray_offsets, early_stop_eps: float):
        n_rays, n_samples = ray_offsets.shape[0] - 1, sigmas.shape[0]
        dev = sigmas.device
        rgb = torch.empty(n_rays, 3, dtype=torch.float32, device=dev)
        opacity = torch.empty(n_rays, dtype=torch.float32, device=dev)
        depth = torch.empty(n_rays, dtype=torch.float32, device=dev)
        trans = torch.empty(n_samples, dtype=torch.float32, device=dev)
        weights = torch.zeros(n_samples, dtype=torch.float32, device=dev)  # padding rows stay 0
        _wp.launch(
            K.composite_forward, n_rays,
            [sigmas, rgbs, t_starts, t_ends, ray_offsets, float(early_stop_eps), rgb, opacity, depth, trans, weights],
            _wp.device_of(sigmas), block_dim=_BLOCK,
        )
        ctx.save_for_backward(sigmas, rgbs, t_starts, t_ends, ray_offsets, trans)
        ctx.set_materialize_grads(False)
        return rgb, opacity, depth, weights

    @staticmethod
    def backward(ctx, g_rgb, g_opacity, g_depth, g_weights):
        sigmas, rgbs, t_starts, t_ends, ray_offsets, trans = ctx.saved_tensors  # checks for in-place changes
        grads = [None if g is None else g.float().contiguous() for g in (g_rgb, g_opacity, g_depth, g_weights)]
        has_grads = sum(1 << k for k, g in enumerate(grads) if g is not None)
        if has_grads == 0:
            return None, None, None, None, None, None
        # Zeros: padding rows past the last ray (see ngp_warp.prune) get no gradient.
        grad_sigmas = torch.zeros_like(sigmas)
        grad_rgbs = torch.zeros_like(rgbs)
        _wp.launch(
            K.composite_backward, ray_offsets.shape[0] - 1,
            [sigmas, rgbs, t_starts, t_ends, ray_offsets, trans, *grads, has_grads, grad_sigmas, grad_rgbs],
            _wp.device_of(sigmas), block_dim=_BLOCK,
        )
        return grad_sigmas, grad_rgbs, None, None, None, None


def composite_packed(
    sigmas: torch.Tensor,
    rgbs: torch.Tensor,
    t_starts: torch.Tensor,
    t_ends: torch.Tensor,
    ray_offsets: torch.Tensor,
    early_stop_eps: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`ngp_warp.composite` on validated, contiguous float32 samples (S ≥ 1) given by
    ``ray_offsets`` [n_rays + 1] int32 (as from :func:`ngp_warp.ray_marching`), skipping the
    conversion from ray indices.

    Returns ``(rgb [n_rays, 3], opacity [n_rays], depth [n_rays], weights [S])``, all
    differentiable w.r.t. ``sigmas`` and ``rgbs``.
    """
    return _Composite.apply(sigmas, rgbs, t_starts, t_ends, ray_offsets, float(early_stop_eps))


def ray_offsets_from_indices(ray_indices: torch.Tensor, n_rays: int) -> torch.Tensor:
    """[S] int64 sorted ray indices (S ≥ 1) → [n_rays + 1] int32 offsets, on the device, no sync."""
    offsets = torch.empty(n_rays + 1, dtype=torch.int32, device=ray_indices.device)
    _wp.launch(
        K.offsets_from_indices, ray_indices.shape[0], [ray_indices, ray_indices.shape[0], n_rays, offsets],
        _wp.device_of(ray_indices), block_dim=_BLOCK,
    )
    return offsets


def _background(background, n_rays: int, device: torch.device) -> torch.Tensor | None:
    if background is None:
        return None
    bg = torch.as_tensor(background, dtype=torch.float32, device=device)
    if bg.dim() == 0:
        bg = bg.expand(3)
    if tuple(bg.shape) not in ((3,), (n_rays, 3)):
        raise ValueError(f"background must be a float, [3] or [{n_rays}, 3], got shape {tuple(bg.shape)}")
    return bg


def _check_sigmas(sigmas, n: int, source: str) -> None:
    if not isinstance(sigmas, torch.Tensor) or sigmas.shape[0] != n or sigmas.numel() != n:
        raise ValueError(f"{source} must return sigmas of shape [{n}] or [{n}, 1], "
                         f"got {getattr(sigmas, 'shape', type(sigmas).__name__)}")


def _prune(samples, sigma_fn, grid: OccupancyGrid, early_stop_eps: float, capacity: int | None) -> PrunedSamples:
    with torch.no_grad():
        sigmas = sigma_fn(samples.positions)
    n = samples.n_samples
    _check_sigmas(sigmas, n, "sigma_fn")
    lo, hi = grid.aabb_host[:3], grid.aabb_host[3:]
    centre = tuple(0.5 * (a + b) for a, b in zip(lo, hi))
    return prune_samples(samples, sigmas.reshape(n).float().contiguous(), early_stop_eps, capacity, centre)


def render_rays(
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    grid: OccupancyGrid,
    field_fn: FieldFn,
    *,
    near: float = 0.0,
    far: float = 1e10,
    step_size: float | None = None,
    cone_angle: float = 0.0,
    max_step: float | None = None,
    early_stop_eps: float = 1e-4,
    background=None,
    stratified: bool = False,
    max_samples_per_ray: int | None = None,
    max_samples: int | None = None,
    sigma_fn: Callable[[torch.Tensor], torch.Tensor] | None = None,
    sample_capacity: int | None = None,
    return_samples: bool = False,
    before_sync: Callable[[], None] | None = None,
) -> dict:
    """Render rays through ``grid`` with the radiance field ``field_fn``.

    .. math::

        C_{out} = \\sum_i w_i c_i + b\\,(1 - O), \\qquad O = \\sum_i w_i, \\qquad
        D = \\sum_i w_i \\frac{t^{start}_i + t^{end}_i}{2}

    with :math:`w_i` as in :func:`ngp_warp.composite`.

    Args:
        rays_o: [N, 3] float32 origins. rays_d: [N, 3] float32 unit directions.
        grid: :class:`ngp_warp.OccupancyGrid` on the rays' device.
        field_fn: ``(positions [S, 3] float32, directions [S, 3] float32) → (sigmas [S] or
            [S, 1] ≥ 0, rgbs [S, 3])``; not called when no ray has a sample.
        near, far, step_size, cone_angle, max_step, stratified, max_samples_per_ray, max_samples:
            as in :func:`ngp_warp.ray_marching` (``step_size`` defaults to the box diagonal / 1024).
        early_stop_eps: samples behind transmittance ``< early_stop_eps`` contribute nothing
            (the field is still evaluated on them, unless ``sigma_fn`` prunes them first).
        background: None, a float, [3] or [N, 3] colour blended behind the samples.
        sigma_fn: ``positions [S, 3] → σ [S]``; when given, it is evaluated without gradient on
            every marched sample and only the samples that composite (transmittance in front
            ``≥ early_stop_eps``) go to ``field_fn`` (see :func:`ngp_warp.prune_samples`).
        sample_capacity: with ``sigma_fn``, ``field_fn`` gets exactly this many rows whenever
            any sample was marched (padding rows at the grid's centre, with zero weight), so its
            shapes are fixed; rays that do not fit are dropped and flagged in ``ray_mask``.
        return_samples: also return the packed samples and their differentiable weights.
        before_sync: as in :func:`ngp_warp.ray_marching`: called once, when the march has
            queued its count and before the host waits for it (independent device work there
            hides the synchronisation).

    Returns:
        dict with ``rgb`` [N, 3], ``opacity`` [N], ``depth`` [N] (float32, differentiable w.r.t.
        the field) and ``n_samples`` (int, rows given to ``field_fn``); with ``sigma_fn`` also
        ``n_marched`` (int), ``n_contributing`` ([1] int32 on the device) and ``ray_mask``
        ([N] bool, False for dropped rays, which render as background); with
        ``return_samples`` also ``weights`` [S], ``ray_indices`` [S] int64, ``t_starts`` [S],
        ``t_ends`` [S] and ``ray_offsets`` [N + 1] int32 (samples of ray r are
        ``ray_offsets[r] : ray_offsets[r+1]``; padding rows lie past ``ray_offsets[N]``).
    """
    if early_stop_eps < 0:
        raise ValueError(f"early_stop_eps must be ≥ 0, got {early_stop_eps}")
    if sample_capacity is not None and (sigma_fn is None or sample_capacity < 1):
        raise ValueError("sample_capacity needs a sigma_fn and must be ≥ 1")
    samples = ray_marching(
        rays_o, rays_d, grid, near=near, far=far, step_size=step_size, cone_angle=cone_angle, max_step=max_step,
        stratified=stratified, max_samples_per_ray=max_samples_per_ray, max_samples=max_samples,
        before_sync=before_sync,
    )
    n_rays, dev = rays_o.shape[0], rays_o.device
    bg = _background(background, n_rays, dev)
    extra = {}
    if sigma_fn is not None:
        extra = {"n_marched": samples.n_samples}
        if samples.n_samples > 0:
            pruned = _prune(samples, sigma_fn, grid, early_stop_eps, sample_capacity)
            samples = pruned.samples
            extra.update(ray_mask=pruned.ray_mask, n_contributing=pruned.n_contributing)
        else:
            extra.update(ray_mask=torch.ones(n_rays, dtype=torch.bool, device=dev),
                         n_contributing=torch.zeros(1, dtype=torch.int32, device=dev))
    n_samples = samples.n_samples
    if n_samples == 0:
        rgb = torch.zeros(n_rays, 3, device=dev)
        opacity = torch.zeros(n_rays, device=dev)
        depth = torch.zeros(n_rays, device=dev)
        weights = torch.zeros(0, device=dev)
    else:
        sigmas, rgbs = field_fn(samples.positions, samples.directions)
        _check_sigmas(sigmas, n_samples, "field_fn")
        if not isinstance(rgbs, torch.Tensor) or tuple(rgbs.shape) != (n_samples, 3):
            raise ValueError(f"field_fn must return rgbs of shape [{n_samples}, 3], "
                             f"got {getattr(rgbs, 'shape', type(rgbs).__name__)}")
        if sigmas.dim() != 1:  # [S, 1]; a reshape of [S] would add a node to the backward
            sigmas = sigmas.reshape(n_samples)
        rgb, opacity, depth, weights = composite_packed(
            sigmas.float().contiguous(), rgbs.float().contiguous(),
            samples.t_starts, samples.t_ends, samples.ray_offsets, early_stop_eps,
        )
    if bg is not None:
        rgb = rgb + bg * (1.0 - opacity)[:, None]
    out = {"rgb": rgb, "opacity": opacity, "depth": depth, "n_samples": n_samples, **extra}
    if return_samples:
        out.update(weights=weights, ray_indices=samples.ray_indices, t_starts=samples.t_starts,
                   t_ends=samples.t_ends, ray_offsets=samples.ray_offsets)
    return out
