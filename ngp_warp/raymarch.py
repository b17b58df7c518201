"""Occupancy-grid ray marching: rays → packed samples (no gradient, as in nerfacc).

Each ray is clipped to the coarsest cascade's box and to ``[near, far]``, then stepped

.. math::

    t_{k+1} = t_k + \\Delta t_k, \\qquad
    \\Delta t_k = \\begin{cases} s & \\text{cone\\_angle} = 0 \\\\
    \\mathrm{clip}(t_k \\cdot \\text{cone\\_angle},\\; s,\\; s_{max}) & \\text{otherwise} \\end{cases}

keeping the interval :math:`[t_k, \\min(t_k + \\Delta t_k, t_{far})]` when the cell (of the finest
cascade containing it) of its midpoint is occupied, and jumping over empty cells (DDA).
Samples are produced by count → prefix sum → fill; the only host synchronisation reads the
total sample count to size the outputs.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import warp as wp

from ngp_warp import _wp
from ngp_warp.kernels import raymarch as K
from ngp_warp.occupancy import OccupancyGrid, host_seed

_NO_CAP = 2**31 - 1


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
        if not isinstance(t, torch.Tensor) or t.dim() != 2 or t.shape[1] != 3:
            raise ValueError(f"{name} must be a [N, 3] tensor, got {getattr(t, 'shape', type(t).__name__)}")
        if t.dtype != torch.float32:
            raise ValueError(f"{name} must be float32, got {t.dtype}")
        if t.device != grid.occs.device:
            raise ValueError(f"{name} is on {t.device} but the grid is on {grid.occs.device}")
    if rays_o.shape[0] != rays_d.shape[0]:
        raise ValueError(f"rays_o holds {rays_o.shape[0]} rays but rays_d {rays_d.shape[0]}")


@torch.no_grad()
def ray_marching(
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    grid: OccupancyGrid,
    *,
    near: float = 0.0,
    far: float = 1e10,
    step_size: float | None = None,
    cone_angle: float = 0.0,
    max_step: float | None = None,
    stratified: bool = False,
    max_samples_per_ray: int | None = None,
    max_samples: int | None = None,
) -> RaySamples:
    """March rays through ``grid`` and return the packed samples in occupied cells.

    Args:
        rays_o: [N, 3] float32 origins. rays_d: [N, 3] float32 directions (``t`` is measured in
            units of ``|d|``, so pass unit vectors for world-space steps); zero directions
            produce no samples.
        grid: the occupancy grid, on the rays' device.
        near, far: the ray interval ``[near, far]``, intersected with the coarsest cascade box.
        step_size: the step ``s`` (default :attr:`OccupancyGrid.default_step_size`, the box
            diagonal / 1024, i.e. √3/1024 for the unit cube).
        cone_angle: 0 for fixed steps, else ``Δt = clip(t·cone_angle, step_size, max_step)``
            (instant-ngp uses 1/256 for large scenes).
        max_step: largest cone step (default 1e10, i.e. unbounded).
        stratified: jitter each ray's first sample by ``u·Δt``, ``u ~ U[0, 1)`` (for training;
            seeded from torch's default CPU generator, so ``torch.manual_seed`` reproduces it).
        max_samples_per_ray: keep at most this many samples per ray (default: no cap).
        max_samples: keep at most this many samples in total; rays past the cap lose their tail.

    Returns:
        :class:`RaySamples`.
    """
    _check_rays(rays_o, rays_d, grid)
    step = grid.default_step_size if step_size is None else float(step_size)
    max_step = 1e10 if max_step is None else float(max_step)
    if not step > 0:
        raise ValueError(f"step_size must be positive, got {step_size}")
    if cone_angle < 0 or max_step < step:
        raise ValueError(f"need cone_angle ≥ 0 and max_step ≥ step_size, got {cone_angle}, {max_step}, {step}")
    if not near < far:
        raise ValueError(f"need near < far, got near={near}, far={far}")
    cap = _NO_CAP if max_samples_per_ray is None else int(max_samples_per_ray)
    if cap < 0 or (max_samples is not None and max_samples < 0):
        raise ValueError("max_samples_per_ray and max_samples must be non-negative")

    dev = rays_o.device
    n_rays = rays_o.shape[0]
    offsets = torch.zeros(n_rays + 1, dtype=torch.int32, device=dev)
    device = _wp.device_of(rays_o)
    common = [
        _wp.to_wp(rays_o.contiguous(), dtype=wp.vec3), _wp.to_wp(rays_d.contiguous(), dtype=wp.vec3),
        *grid.warp_views(), grid.resolution, grid.levels,
        float(near), float(far), step, float(cone_angle), max_step, cap,
        int(stratified), host_seed() if stratified else 0,
    ]
    n_samples = 0
    if n_rays > 0:
        counts = torch.empty(n_rays, dtype=torch.int32, device=dev)
        _wp.launch(K.march_rays, n_rays, [0, *common, _wp.to_wp(counts), None, None, None, None, None, None], device)
        torch.cumsum(counts, 0, dtype=torch.int32, out=offsets[1:])
        if max_samples is not None:
            offsets.clamp_(max=int(max_samples))
        n_samples = int(offsets[-1])  # the one host synchronisation: sizes the outputs
    ray_indices = torch.empty(n_samples, dtype=torch.int64, device=dev)
    t_starts = torch.empty(n_samples, dtype=torch.float32, device=dev)
    t_ends = torch.empty(n_samples, dtype=torch.float32, device=dev)
    positions = torch.empty(n_samples, 3, dtype=torch.float32, device=dev)
    directions = torch.empty(n_samples, 3, dtype=torch.float32, device=dev)
    if n_samples > 0:
        _wp.launch(
            K.march_rays, n_rays,
            [1, *common, None, _wp.to_wp(offsets), _wp.to_wp(ray_indices), _wp.to_wp(t_starts), _wp.to_wp(t_ends),
             _wp.to_wp(positions, dtype=wp.vec3), _wp.to_wp(directions, dtype=wp.vec3)],
            device,
        )
    return RaySamples(ray_indices, t_starts, t_ends, positions, directions, offsets)
