""":func:`ngp_warp.ray_marching` as a torch.library op, which ``torch.compile`` traces without a
graph break: the march runs inside the op (its one host sync included), and the fake kernel
gives the sample count as a data-dependent size. The grid is named by number
(:mod:`ngp_warp.op_registry`) and read when the op runs, so a compiled graph sees the grid's
latest update. The march has no gradient."""

from __future__ import annotations

import torch

from ngp_warp.op_registry import lookup


@torch.library.custom_op("ngp_warp::ray_marching", mutates_args=())
def march_op(rays_o: torch.Tensor, rays_d: torch.Tensor, grid: int, near: float, far: float,
             step_size: float | None, cone_angle: float, max_step: float | None, stratified: bool,
             max_samples_per_ray: int | None, max_samples: int | None
             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    from ngp_warp.raymarch import MarchOptions, ray_marching

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
