"""Occupancy-grid ray marching: rays → packed samples (no gradient, as in nerfacc).

Each ray is clipped to the coarsest cascade's box and to ``[near, far]``, then stepped

.. math::

    t_{k+1} = t_k + \\Delta t_k, \\qquad
    \\Delta t_k = \\begin{cases} s & \\text{cone\\_angle} = 0 \\\\
    \\mathrm{clip}(t_k \\cdot \\text{cone\\_angle},\\; s,\\; s_{max}) & \\text{otherwise} \\end{cases}

keeping the interval :math:`[t_k, \\min(t_k + \\Delta t_k, t_{far})]` when the cell (of the finest
cascade containing it) of its midpoint is occupied, and jumping over empty cells (DDA).

On a grid with a scene contraction (``OccupancyGrid(..., contraction=...)``) rays run over
``[near, far]`` (the grid covers all of space) in world space, with steps that span the
contracted length :math:`s` (``step_size``, in contracted units) unless the cone step is longer:

.. math::

    \\Delta t_k = \\max\\big(s / \\|J_C(x_k)\\,(d \\oslash h)\\|,\\;
    \\min(t_k \\cdot \\text{cone\\_angle},\\; s_{max})\\big)

(:func:`ngp_warp.ops.contraction.world_step_length`), and each step is kept when the cell of
:math:`C(x)` at its midpoint is occupied (one lookup per step, no DDA). The samples stay in
world space; the field contracts them.
Samples are produced by count → prefix sum → fill; the only host synchronisation reads the
total sample count to size the outputs. Several threads march one ray, each over a segment of
its steps (:class:`MarchSchedule`; cone steps too, whose t_k has a closed form in k); the samples
do not depend on the split, but for a step whose midpoint lies within float rounding of the face
of a cell or of an empty block the march skips, which may fall either side (8–17 rays of 25.6
million in 40 of lego's views, one sample each).
The count records each segment's kept steps as a bit mask, from which the fill writes the
samples without marching again, and a large launch's positions and directions take a pass of
their own (:mod:`ngp_warp.ops.march_schedule`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

import warp as wp

from ngp_warp import _wp
from ngp_warp.ops.contraction import KINDS
from ngp_warp.kernels import raymarch as K
from ngp_warp.kernels import raymarch_funcs as KF
from ngp_warp.ops.occupancy import OccupancyGrid, host_seed
from ngp_warp.ops.march_schedule import NO_CAP, SCHEDULES, MarchSchedule, ray_segments
from ngp_warp.ops.op_registry import lookup

@dataclass
class RaySamples:
    """Packed samples of ``n_rays`` rays, sorted by ray then by distance.

    Attributes:
        ray_indices: [S] int64, the ray of each sample (non-decreasing).
        t_starts, t_ends: [S] float32 interval of each sample along its ray.
        positions: [S, 3] float32 interval midpoints ``o + d·(t_start + t_end)/2``.
        directions: [S, 3] float32 the ray direction of each sample (as given).
        ray_offsets: [n_rays + 1] int32, samples of ray r are ``ray_offsets[r] : ray_offsets[r+1]``.
    """

    ray_indices: torch.Tensor
    t_starts: torch.Tensor
    t_ends: torch.Tensor
    positions: torch.Tensor
    directions: torch.Tensor
    ray_offsets: torch.Tensor

    @property
    def n_samples(self) -> int:
        return self.t_starts.shape[0]


def _check_rays(rays_o: torch.Tensor, rays_d: torch.Tensor, grid: OccupancyGrid) -> None:
    if not isinstance(grid, OccupancyGrid):
        raise ValueError(f"grid must be an OccupancyGrid, got {type(grid).__name__}")
    for name, t in (("rays_o", rays_o), ("rays_d", rays_d)):
        if not isinstance(t, torch.Tensor) or t.dim() < 1 or t.shape[-1] != 3:
            raise ValueError(f"{name} must be a [..., 3] tensor, got {getattr(t, 'shape', type(t).__name__)}")
        if t.dtype != torch.float32:
            raise ValueError(f"{name} must be float32, got {t.dtype}")
        if t.device != grid.occs.device:
            raise ValueError(f"{name} is on {t.device} but the grid is on {grid.occs.device}")
    if rays_o.shape != rays_d.shape:
        raise ValueError(f"rays_o has shape {list(rays_o.shape)} but rays_d {list(rays_d.shape)}")


def _read_total(total: torch.Tensor, before_sync: Callable[[], None] | None) -> list[int]:
    """``total`` ([k] int32 on the device: the count, then any check flags) on the host. On CUDA
    with ``before_sync``, through a pinned copy and an event recorded before ``before_sync``'s
    work, so that the host waits for the count only, while the GPU goes on with that work."""
    if before_sync is None:
        return total.tolist()
    if not total.is_cuda:
        before_sync()
        return total.tolist()
    host = torch.empty(total.shape, dtype=total.dtype, pin_memory=True)
    host.copy_(total, non_blocking=True)
    copied = torch.cuda.Event()
    copied.record(torch.cuda.current_stream(total.device))  # the copy's stream, whichever GPU is current
    before_sync()
    copied.synchronize()
    return host.tolist()


_RAY_PROBLEMS = ("rays_o holds NaN or infinite origins", "rays_d holds NaN or infinite directions",
                 "rays_d holds directions that are not unit vectors (|d| off 1 by more than 1e-3; "
                 "normalise them: rays_d / rays_d.norm(dim=-1, keepdim=True))")


def _ray_flags(rays_o: torch.Tensor, rays_d: torch.Tensor, unit_directions: bool) -> torch.Tensor:
    """[1] int32 on the device, bit k set for problem k of :data:`_RAY_PROBLEMS` (no sync)."""
    flags = (~torch.isfinite(rays_o)).any().int() + 2 * (~torch.isfinite(rays_d)).any().int()
    if unit_directions:
        flags = flags + 4 * ((rays_d * rays_d).sum(-1) - 1.0).abs().gt(2e-3).any().int()
    return flags.reshape(1)


def _raise_flags(flags: int) -> None:
    problems = [p for k, p in enumerate(_RAY_PROBLEMS) if flags >> k & 1]
    if problems:
        raise ValueError("; ".join(problems))


_configs: dict[tuple, KF.MarchConfig] = {}


def _march_config(*values) -> KF.MarchConfig:
    """The kernel's settings struct for ``values`` (in field order), built once per configuration."""
    config = _configs.get(values)
    if config is None:
        if len(_configs) >= 64:
            _configs.clear()
        config = _configs[values] = KF.MarchConfig()
        for name, value in zip(KF.MarchConfig.vars, values):
            setattr(config, name, wp.vec3(*value) if isinstance(value, tuple) else value)
    return config


@dataclass(frozen=True)
class MarchOptions:
    """How :func:`ray_marching` (and :func:`ngp_warp.render_rays`) step along the rays.

    Attributes:
        near, far: the ray interval ``[near, far]``, intersected with the coarsest cascade box.
        step_size: the step ``s`` (None: :attr:`OccupancyGrid.default_step_size`, the box
            diagonal / 1024, i.e. √3/1024 for the unit cube); in contracted units on a grid
            with a contraction.
        cone_angle: 0 for fixed steps, else ``Δt = clip(t·cone_angle, step_size, max_step)``
            (instant-ngp uses 1/256 for large scenes).
        max_step: largest cone step (None: 1e10, i.e. unbounded); with a contraction it
            bounds only the cone term.
        stratified: jitter each ray's first sample by ``u·Δt``, ``u ~ U[0, 1)`` (for training;
            seeded from torch's default CPU generator, so ``torch.manual_seed`` reproduces it).
        max_samples_per_ray: keep at most this many samples per ray (None: no cap).
        max_samples: keep at most this many samples in total; rays past the cap lose their tail.
    """

    near: float = 0.0
    far: float = 1e10
    step_size: float | None = None
    cone_angle: float = 0.0
    max_step: float | None = None
    stratified: bool = False
    max_samples_per_ray: int | None = None
    max_samples: int | None = None


def _contraction(grid: OccupancyGrid) -> tuple[int, tuple, tuple]:
    """(kind flag or NO_CONTRACTION, inner box centre, half extents) of ``grid`` for MarchConfig."""
    if grid.contraction is None:
        return KF.NO_CONTRACTION, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)
    box = grid.inner_aabb_host
    return (KINDS[grid.contraction], tuple((box[a] + box[a + 3]) / 2 for a in range(3)),
            tuple((box[a + 3] - box[a]) / 2 for a in range(3)))


def _march_steps(march: MarchOptions, grid: OccupancyGrid) -> tuple[float, float, int]:
    """(step, max_step, per-ray cap) of ``march`` on ``grid``; ValueError for a setting out of range."""
    if not isinstance(march, MarchOptions):
        raise ValueError(f"march must be a MarchOptions, got {type(march).__name__}")
    step = grid.default_step_size if march.step_size is None else float(march.step_size)
    max_step = 1e10 if march.max_step is None else float(march.max_step)
    if not step > 0:
        raise ValueError(f"step_size must be positive, got {march.step_size}")
    if march.cone_angle < 0 or max_step < step:
        raise ValueError(f"need cone_angle ≥ 0 and max_step ≥ step_size, "
                         f"got {march.cone_angle}, {max_step}, {step}")
    if not march.near < march.far:
        raise ValueError(f"need near < far, got near={march.near}, far={march.far}")
    cap = NO_CAP if march.max_samples_per_ray is None else int(march.max_samples_per_ray)
    if cap < 0 or (march.max_samples is not None and march.max_samples < 0):
        raise ValueError("max_samples_per_ray and max_samples must be non-negative")
    return step, max_step, cap


def _sample_total(total: torch.Tensor, capacity: int | None, before_sync, flags: torch.Tensor | None) -> int:
    """The sample count ([1] int32 on the device) on the host, with the validation ``flags``
    checked (the march's one host synchronisation); with a ``capacity`` and no flags, no sync
    (returns 0: the caller sizes the output to the capacity)."""
    if flags is not None:
        total = torch.cat([total, flags])
    elif capacity is not None:
        if before_sync is not None:
            before_sync()
        return 0
    n_samples, *read = _read_total(total, before_sync)
    if read:
        _raise_flags(read[0])
    return n_samples


def _empty_or_full(n: int, dtype: torch.dtype, value, fill: bool, device) -> torch.Tensor:
    """[n] tensor: uninitialised, or filled with ``value`` (a capacity's padding rows)."""
    if fill:
        return torch.full((n,), value, dtype=dtype, device=device)
    return torch.empty(n, dtype=dtype, device=device)


@torch.no_grad()
def ray_marching(
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    grid: OccupancyGrid,
    march: MarchOptions = MarchOptions(),
    *,
    before_sync: Callable[[], None] | None = None,
    validate: bool = True,
    unit_directions: bool = False,
    capacity: int | None = None,
) -> RaySamples:
    """March rays through ``grid`` and return the packed samples in occupied cells.

    Args:
        rays_o: [N, 3] float32 origins. rays_d: [N, 3] float32 directions (``t`` is measured in
            units of ``|d|``, so pass unit vectors for world-space steps); zero directions
            produce no samples. Any strides; leading dimensions [..., 3] are flattened, and
            the samples' ray indices count the flattened rays.
        grid: the occupancy grid, on the rays' device. march: :class:`MarchOptions`.
        before_sync: called once, after the count pass is queued and before the host waits for
            the total, to keep the GPU busy through the sync (the trainer queues the previous
            step's optimizer update there); it must not change the rays or the grid.
        validate: check on the device that origins and directions are finite (with
            ``unit_directions``, ``|d| = 1`` within 1e-3), read with the count (no extra sync);
            ValueError otherwise. Loops that make their own rays pass False.
        unit_directions: with ``validate``, require unit directions (as ``render_rays`` does).
        capacity: None sizes the output to the count (the one host sync); an int gives that many
            rows without the sync (unless ``validate``): the tail cut as by ``max_samples``, padding
            rows past ``ray_offsets[N]`` (ray N, interval [0, 0], zeros; weight 0 when composited).

    Returns:
        :class:`RaySamples`.
    """
    _check_rays(rays_o, rays_d, grid)
    if rays_o.dim() != 2 or not (rays_o.is_contiguous() and rays_d.is_contiguous()):  # [..., 3], any strides
        rays_o, rays_d = (t.reshape(-1, 3).contiguous() for t in (rays_o, rays_d))
    if torch.compiler.is_compiling():  # the torch.library op: no graph break
        return RaySamples(*march_op(rays_o.detach(), rays_d.detach(), id(grid), float(march.near), float(march.far), march.step_size,
                                    float(march.cone_angle), march.max_step, bool(march.stratified),
                                    march.max_samples_per_ray, march.max_samples))
    step, max_step, cap = _march_steps(march, grid)
    if capacity is not None and (type(capacity) is not int or capacity < 1):
        raise ValueError(f"capacity must be None or an int ≥ 1, got {capacity!r}")
    near, far, cone_angle = float(march.near), float(march.far), float(march.cone_angle)
    dev = rays_o.device
    n_rays = rays_o.shape[0]
    device = _wp.device_of(rays_o)
    schedule = SCHEDULES["cpu" if device == "cpu" else "cuda"]
    n_seg, seg_steps = ray_segments(schedule, grid, near, far, step, cone_angle, max_step, n_rays)
    config = _march_config(grid.resolution, grid.levels, grid.n_mips, grid.mip_cells, near, far, step,
                           cone_angle, max_step, cap, int(march.stratified), n_seg, seg_steps, *_contraction(grid))
    seed = host_seed() if march.stratified else 0
    common = [rays_o, rays_d, grid.aabb, grid.bitfield, grid.march_mips(), config, seed]
    n_items = n_rays * n_seg  # one per (ray, segment)
    seg_ints = torch.empty(2 * n_items + 1, dtype=torch.int32, device=dev)  # one allocation for both
    seg_counts, seg_offsets = seg_ints[:n_items], seg_ints[n_items:]
    offsets = torch.empty(n_rays + 1, dtype=torch.int32, device=dev)
    words = -(-seg_steps // 64)  # of the step masks the fill writes from (MarchSchedule)
    masks = torch.empty(n_items * words, dtype=torch.int64, device=dev) if words <= schedule.mask_words else None
    n_samples = 0
    if n_rays > 0:
        _wp.launch(K.march_rays, n_items, [0, *common, seg_counts, seg_offsets, None, *[None] * 5, masks], device)
        if cap != NO_CAP:  # keep each ray's first `cap` samples: cap the running count within the ray
            in_ray = torch.cumsum(seg_counts.view(n_rays, n_seg), 1, dtype=torch.int32).clamp_(max=cap)
            seg_counts = torch.diff(in_ray, dim=1, prepend=in_ray.new_zeros(n_rays, 1)).reshape(-1)
        torch.cumsum(seg_counts, 0, dtype=torch.int32, out=seg_offsets[1:])
        limit = min(x for x in (march.max_samples, capacity, NO_CAP) if x is not None)
        if limit != NO_CAP:
            seg_offsets.clamp_(max=int(limit))
        n_samples = _sample_total(seg_offsets[-1:], capacity, before_sync,
                                  _ray_flags(rays_o, rays_d, unit_directions) if validate else None)
    elif before_sync is not None:
        before_sync()
    return _fill(n_samples if capacity is None else capacity, n_rays, n_items, capacity is not None, common,
                 seg_offsets, offsets, masks, schedule, device)


def _fill(n_samples: int, n_rays: int, n_items: int, padded: bool, common: list, seg_offsets: torch.Tensor,
          offsets: torch.Tensor, masks: torch.Tensor | None, schedule: MarchSchedule, device: str) -> RaySamples:
    """The march's fill pass: ``n_samples`` output rows (``padded``: a capacity's, initialised as
    padding) written by the ``n_items`` (ray, segment) threads from the count pass's
    ``seg_offsets`` [n_items + 1] int32 and step ``masks`` [n_items × words] int64 (or None); the rays'
    ``offsets`` [n_rays + 1] int32 are written too (zeros when nothing was marched). The
    ``schedule`` says when positions and directions take a pass of their own."""
    dev = offsets.device
    ray_indices = _empty_or_full(n_samples, torch.int64, n_rays, padded, dev)
    floats = _empty_or_full(8 * n_samples, torch.float32, 0, padded, dev)  # contiguous parts
    t_starts, t_ends = floats[:n_samples], floats[n_samples : 2 * n_samples]
    positions = floats[2 * n_samples : 5 * n_samples].view(n_samples, 3)
    directions = floats[5 * n_samples :].view(n_samples, 3)
    if n_samples > 0 and n_rays > 0:
        apart = schedule.points_apart_from is not None and n_samples >= schedule.points_apart_from
        points = [None, None] if apart else [positions, directions]
        _wp.launch(K.march_rays, n_items,
                   [1, *common, None, seg_offsets, offsets, ray_indices, t_starts, t_ends, *points, masks], device)
        if apart:
            _wp.launch(K.sample_points, n_samples,
                       [*common[:2], ray_indices, t_starts, t_ends, positions, directions], device)
    else:
        offsets.zero_()
    return RaySamples(ray_indices, t_starts, t_ends, positions, directions, offsets)


# ray_marching as a torch.library op, which torch.compile traces without a graph break: the
# march runs inside the op (its one host sync included), and the fake kernel gives the sample
# count as a data-dependent size. The grid is named by number (ngp_warp.ops.op_registry) and read
# when the op runs, so a compiled graph sees the grid's latest update. The march has no gradient.
@torch.library.custom_op("ngp_warp::ray_marching", mutates_args=())
def march_op(rays_o: torch.Tensor, rays_d: torch.Tensor, grid: int, near: float, far: float,
             step_size: float | None, cone_angle: float, max_step: float | None, stratified: bool,
             max_samples_per_ray: int | None, max_samples: int | None
             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    march = MarchOptions(near=near, far=far, step_size=step_size, cone_angle=cone_angle, max_step=max_step,
                         stratified=stratified, max_samples_per_ray=max_samples_per_ray, max_samples=max_samples)
    s = ray_marching(rays_o, rays_d, lookup(grid), march, validate=False)
    # the march packs its outputs in one buffer; an op's outputs may not alias each other
    return tuple(t.clone() for t in (s.ray_indices, s.t_starts, s.t_ends, s.positions, s.directions, s.ray_offsets))


@march_op.register_fake
def _(rays_o, rays_d, grid, near, far, step_size, cone_angle, max_step, stratified, max_samples_per_ray,
      max_samples):
    n = torch.library.get_ctx().new_dynamic_size()
    return (rays_o.new_empty(n, dtype=torch.int64), rays_o.new_empty(n), rays_o.new_empty(n),
            rays_o.new_empty(n, 3), rays_o.new_empty(n, 3), rays_o.new_empty(rays_o.shape[0] + 1, dtype=torch.int32))
