"""A scene's radiance model: the field, its occupancy grid, and how rays march through them.

Training (:mod:`ngp_warp.training.trainer`) and inference (:mod:`ngp_warp.outputs.renderer`) render through the
one :meth:`RadianceModel.render`.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable

import torch

from ngp_warp.data.loading import Scene
from ngp_warp.ops.field import FieldConfig, NGPField
from ngp_warp.ops.occupancy import OccupancyGrid
from ngp_warp.ops.raymarch import MarchOptions
from ngp_warp.ops.render import FieldFn, render_rays
from ngp_warp.training.scene_defaults import cone_steps, contraction_box

FAR = 1e4  # far distance of every ray (world units); the grid ends rays long before it


class RadianceModel:
    """The field and occupancy grid of one scene, with the settings a ray is marched by.

    Args:
        field: the radiance field. grid: its occupancy grid (same device).
        march: near, far, step and cone angle (``stratified`` is chosen per render).
        early_stop_eps: as in :func:`ngp_warp.render_rays`.
        mlp_precision: the MLPs' matmul precision on CUDA, ``"bf16"``, ``"tf32"`` or ``"fp32"``
            (the CPU runs fp32).
    """

    def __init__(self, field: NGPField, grid: OccupancyGrid, march: MarchOptions, *,
                 early_stop_eps: float = 1e-4, mlp_precision: str = "fp32"):
        self.field = field
        self.grid = grid
        self.march = dataclasses.replace(march, stratified=False)
        self._stratified = dataclasses.replace(march, stratified=True)  # made once: no per-step objects
        self.early_stop_eps = early_stop_eps
        self.mlp_precision = mlp_precision
        # the most marched samples per ray the last rendered view had: the next view's first
        # chunk is sized by it (see ngp_warp.outputs.renderer.ChunkSizer), None before any view
        self.view_samples_per_ray: float | None = None
        # the mean samples per ray the last view shaded: the next view's first round of
        # encoding is sized by it (see ngp_warp.outputs.renderer.auto_first_round), None before any view
        self.view_shaded_per_ray: float | None = None

    def start_rays_at(self, near: float) -> None:
        """March every later ray from ``near`` (world units, above 0 and below the far distance;
        ValueError otherwise), as a render closer to the subject than the training cameras needs."""
        if not 0 < near < self.march.far:
            raise ValueError(f"near must be above 0 and below the rays' far distance {self.march.far:g}, got {near!r}")
        self.march = dataclasses.replace(self.march, near=near)
        self._stratified = dataclasses.replace(self._stratified, near=near)

    @classmethod
    def for_scene(cls, scene: Scene, field_config: FieldConfig, device: torch.device, *, grid_resolution: int,
                  steps_per_diagonal: int, cone_angle: float, contraction: str | None = None,
                  contraction_fit: str = "cameras",
                  **settings) -> RadianceModel:
        """A fresh field and occupancy grid for ``scene`` on ``device``, marched from the scene's
        near distance to :data:`FAR`, one appearance code per training image when
        ``field_config.appearance_dim`` > 0. ``settings``: the constructor's keywords.

        Without ``contraction``: the field over ``scene.aabb``, the grid over its occupancy box
        (its cascades), the step the finest cascade's diagonal over ``steps_per_diagonal``
        (instant-ngp's √3/1024 of its unit cube), not the whole field box's, which is aabb_scale
        times larger for instant-ngp scenes. With ``contraction`` (``"l2"`` or ``"linf"``): field
        and grid in contracted space around :func:`~ngp_warp.training.scene_defaults.contraction_box`, the
        step the contracted grid's diagonal over ``steps_per_diagonal``. Cone steps
        (``cone_angle`` > 0) grow up to :func:`~ngp_warp.training.scene_defaults.cone_steps`' largest step.
        """
        box = scene.occupancy_aabb if contraction is None else contraction_box(scene, contraction_fit)
        field = NGPField(scene.aabb if contraction is None else box, field_config, contraction=contraction,
                         n_images=len(scene.train)).to(device)
        levels = scene.occupancy_levels if contraction is None else 1
        grid = OccupancyGrid(box, resolution=grid_resolution, levels=levels, contraction=contraction).to(device)
        if contraction is None:
            step_size = float((box[3:] - box[:3]).norm()) / steps_per_diagonal
        else:
            step_size = grid.default_step_size * 1024 / steps_per_diagonal
        max_step = cone_steps(scene, contraction)[2] if cone_angle > 0 else None
        march = MarchOptions(near=scene.near, far=FAR, step_size=step_size, cone_angle=cone_angle, max_step=max_step)
        return cls(field, grid, march, **settings)

    def march_options(self, stratified: bool) -> MarchOptions:
        """The model's march, with jittered first samples when ``stratified`` (both made once)."""
        return self._stratified if stratified else self.march

    @property
    def device(self) -> torch.device:
        return self.field.aabb.device

    @property
    def step_size(self) -> float:
        """The marching step in world units: with a contraction, the world length of the march's
        step (in contracted units) inside the inner box, its mean half side times it."""
        if self.grid.contraction is None:
            return self.march.step_size
        inner = self.grid.inner_aabb_host
        half_side = sum(hi - lo for lo, hi in zip(inner[:3], inner[3:])) / 6.0
        return self.march.step_size * half_side

    @property
    def learns_background(self) -> bool:
        """Whether the field models the far background (unbounded, contracted space, or a
        learned environment beyond a bounded box): opaque training images are then fitted and
        rendered over the field's learned environment
        (:meth:`~ngp_warp.ops.field.NGPField.background`; black for a field without one), not white."""
        return self.grid.contraction is not None or self.field.environment is not None

    @contextlib.contextmanager
    def precision(self):
        """The MLPs' matmul precision on CUDA (master weights stay float32). bf16 autocast runs
        without its cast cache, which CUDA-graph capture requires: the weights' casts are then
        part of the captured graphs (a few kernels over 13 k weights)."""
        mode = self.mlp_precision
        if self.device.type != "cuda" or mode == "fp32":
            yield
        elif mode == "bf16":
            with torch.autocast("cuda", dtype=torch.bfloat16, cache_enabled=False):
                yield
        else:  # tf32 (TrainConfig.check names the modes)
            saved = torch.backends.cuda.matmul.allow_tf32
            torch.backends.cuda.matmul.allow_tf32 = True
            try:
                yield
            finally:
                torch.backends.cuda.matmul.allow_tf32 = saved

    def render(self, rays_o: torch.Tensor, rays_d: torch.Tensor, field_fn: FieldFn, *, background=None,
               stratified: bool = False, sigma_fn: Callable[[torch.Tensor], torch.Tensor] | None = None,
               sample_capacity: int | None = None, return_samples: bool = False,
               before_sync: Callable[[], None] | None = None, ray_images: torch.Tensor | None = None,
               near_gradient_distance: float = 0.0) -> dict:
        """Rays ``rays_o``, ``rays_d`` ([N, 3] float32, unit directions) through the grid,
        evaluated by ``field_fn`` (the field, or a graphed stand-in for it): the dict of
        :func:`ngp_warp.render_rays`, whose other keywords these are, with this model's march
        (``stratified``: jittered first samples) and early-stop threshold."""
        return render_rays(
            rays_o, rays_d, self.grid, field_fn, self.march_options(stratified),
            early_stop_eps=self.early_stop_eps, background=background,
            sigma_fn=sigma_fn, sample_capacity=sample_capacity,
            return_samples=return_samples, before_sync=before_sync, ray_images=ray_images,
            near_gradient_distance=near_gradient_distance,
            validate=False,  # the trainer's and renderer's own rays: checked where they are made
        )
