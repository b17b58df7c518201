"""Per-scene training: sample rays across all training images, render, fit, keep the grid fresh.

:class:`Trainer` puts together the parts: the settings (:mod:`ngp_warp.training.config`), the model
(field, occupancy grid, marching: :mod:`ngp_warp.training.model`), the optimizer state
(:mod:`ngp_warp.training.field_optimizer`), the step's parts (:mod:`ngp_warp.training.train_step`) and the image
renderer (:mod:`ngp_warp.outputs.renderer`).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence

import torch
from ngp_warp.progress import progress as progress_bar

from ngp_warp.ops.batch import sample_pixels
from ngp_warp.training.camera_refinement import CameraRefinement
from ngp_warp.ops.optim import Adam
from ngp_warp.training.config import TrainConfig, default_device, default_target_samples, resolve_defaults
from ngp_warp.data.cameras import pinhole_border_error
from ngp_warp.data.loading import Scene, Split
from ngp_warp.ops.distortion import distortion_loss_packed
from ngp_warp.ops.field import NGPField
from ngp_warp.training.field_optimizer import FieldOptimizer
from ngp_warp.training.memory_estimate import check_fits
from ngp_warp.training.model import RadianceModel
from ngp_warp.ops.occupancy import OccupancyGrid
from ngp_warp.ops.ray_loss import ray_loss
from ngp_warp.outputs.renderer import render_view
from ngp_warp.training.scene_defaults import start_environment, with_backdrop_alpha
from ngp_warp.training.train_step import (HostCopy, RayCount, StepPhases, TrainingDiverged, TrainingField, backward,
                                         pixels_kept, rays_kept, uses_graphs)

READOUT_EVERY = 10  # steps between progress readouts (each copies the loss to the host, read at the next)


class Trainer:
    """The model, optimizer state and ray count of one scene; :meth:`step` is one update.

    Args:
        scene: the scene (its training split moves to ``device``).
        config: the settings (checked; settings left to None are resolved for the device and
            the scene into :attr:`config`, the caller's object is left alone).
        device: ``cpu``, ``cuda`` or ``cuda:N``; None picks CUDA when present.

    Raises:
        ValueError: naming a setting out of range;
            :class:`~ngp_warp.training.memory_estimate.SettingsTooLarge` for settings that cannot fit in memory.
    """

    def __init__(self, scene: Scene, config: TrainConfig | None = None, device: str | None = None):
        self.device = torch.device(device or default_device())
        self.config = cfg = resolve_defaults(config or TrainConfig(), scene, self.device.type)
        self.scene = scene = dataclasses.replace(scene.with_aabb_scale(cfg.aabb_scale), near=cfg.near)
        check_fits(cfg, scene, self.device)  # SettingsTooLarge before allocating
        torch.manual_seed(cfg.seed)
        train = scene.train
        if cfg.backdrop_alpha and train.images.shape[-1] == 3:  # trained over random backgrounds
            train = dataclasses.replace(train, images=with_backdrop_alpha(train.images))
        self.train_split: Split = train.to(self.device)
        self.model = RadianceModel.for_scene(
            scene, cfg.field, self.device, grid_resolution=cfg.grid_resolution,
            steps_per_diagonal=cfg.steps_per_diagonal, cone_angle=cfg.cone_angle, contraction=cfg.contraction,
            contraction_fit=cfg.contraction_fit, early_stop_eps=cfg.early_stop_eps, mlp_precision=cfg.mlp_precision)
        # opaque images of contracted scenes: fitted over the field's learned environment (view_background)
        self.black_background = self.model.learns_background and self.train_split.images.shape[-1] == 3
        if self.field.environment is not None:
            start_environment(self.field.environment, self.train_split.images, self.train_split.masks)
        self.batch_images: torch.Tensor | None = None  # [p k] int64 image per ray of the last batch
        self.batch_kept: torch.Tensor | None = None  # [p k] bool: the ray's pixel is one to train on
        self.target_samples = default_target_samples(cfg, self.device.type)
        self.rays = RayCount(cfg.initial_rays, cfg.max_rays, self.target_samples, self.device)
        self.weights = FieldOptimizer(self.field, cfg.lr, cfg.weight_decay, cfg.weight_average, cfg.lazy_table_adam,
                                      cfg.lr_warmup)
        self.cameras, self.camera_adam = self._camera_refinement(cfg)
        self.training_field = TrainingField(self.field, self.target_samples, uses_graphs(cfg, self.device.type))
        self.step_count = 0
        self.train_seconds = 0.0
        self._readout = HostCopy(2, self.device)  # a readout's loss and mse, on their way to the host
        # one row per readout: step, training seconds, loss, training PSNR, rays, samples
        self.curve: list[tuple[int, float, float, float, int, int]] = []
        # data-parallel training (ngp_warp.training.distributed.make_data_parallel) sets these hooks:
        self.ray_stream = 0  # this rank's ray seed stream
        self.gradient_reduction: Callable[[], None] | None = None  # after every backward, on every rank
        self.shared_clock: Callable[[int], float] | None = None  # step → training seconds all ranks agree on
        self.phases = StepPhases(
            sample_batch=self.sample_batch, render=self._render_batch, grid_update=self._grid_update,
            density=self.training_field.density, field=self.training_field, optimizer_update=self.weights.flush,
            loss=ray_loss, distortion=distortion_loss_packed, backward=backward)
        split = self.train_split
        self.grid.mark_invisible_cells(split.c2w, split.intrinsics, split.width, split.height)
        if cfg.grid_seen_only and not split.fisheye:  # a fisheye lens has no pinhole test
            lens = pinhole_border_error(split.intrinsics, split.distortion, split.width, split.height) \
                if split.has_distortion else 0.0
            self.grid.count_seen_only(split.c2w, split.intrinsics, split.width, split.height,
                                      near=self.model.march.near, margin=1.0 + lens)

    def _camera_refinement(self, cfg: TrainConfig) -> tuple[CameraRefinement | None, Adam | None]:
        """The training images' pose corrections and their optimizer, with ``camera_refinement``
        (bounded fields only: positions reach a contracted field without gradient)."""
        if not cfg.camera_refinement:
            return None, None
        if cfg.contraction is not None:
            raise ValueError("camera_refinement needs a bounded scene (contraction=none); "
                             f"this one is contracted ({cfg.contraction})")
        cameras = CameraRefinement(len(self.train_split.names), self.device)
        return cameras, cameras.optimizer(cfg.camera_lr)

    @property
    def field(self) -> NGPField:
        return self.model.field

    @property
    def grid(self) -> OccupancyGrid:
        return self.model.grid

    def instrument(self, wrap: Callable[[str, Callable], Callable]) -> None:
        """Route every phase of the following steps through ``wrap(phase name, call)`` (see
        :class:`ngp_warp.training.train_step.StepPhases`), e.g. to time them."""
        self.phases = self.phases.wrapped(wrap)

    # -- one optimisation step -------------------------------------------------------------
    def sample_batch(self, n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Rays through random pixels across all training images → (rays_o, rays_d [p k, 3],
        target rgb and background [p, 3] per pixel) for p = max(1, n div k) pixels of k =
        supersample² rays each, drawn in one launch from a seed that mixes the config's seed
        with the step count (and :attr:`ray_stream`). Where the field learns the background
        (:attr:`RadianceModel.learns_background`, opaque images) it is the field's environment
        (:meth:`NGPField.background`, differentiable), or black without one. With appearance
        codes, each ray's training image goes to :attr:`batch_images` (for :meth:`_render_batch`).
        With camera refinement the rays are corrected by their image's pose correction
        (:attr:`cameras`), differentiably. With training masks, :attr:`batch_kept` says which rays count."""
        seed = (self.step_count * 0x9E3779B1 + self.config.seed * 0x85EBCA6B
                + self.ray_stream * 0xC2B2AE35) & 0x7FFFFFFF
        sub = self.config.supersample
        b = sample_pixels(self.train_split, max(1, n // (sub * sub)), seed, sub)
        self.batch_kept = pixels_kept(self.train_split.masks, b.pixels, sub)
        images = None
        if self.field.appearance is not None or self.cameras is not None:
            images = b.pixels[:, 0].long().repeat_interleave(sub * sub)
        self.batch_images = images if self.field.appearance is not None else None
        rays_o, rays_d = (b.rays_o, b.rays_d) if self.cameras is None else self.cameras.rays(images, b.rays_o, b.rays_d)
        background = b.background
        if self.black_background:  # the field's environment along each pixel's first sub-ray, or black
            environment = self.field.environment is not None
            background = self.field.background(rays_d[::sub * sub]) if environment else background.zero_()
        return rays_o, rays_d, b.target, background

    def _grid_update(self, step: int, density_fn) -> bool:
        """Refresh the grid at ``step`` (``density_fn``: [M, 3] float32 → σ [M]); threshold 0 while open."""
        cfg = self.config
        threshold = 0.0 if step < cfg.occupancy_open_steps else cfg.occupancy_threshold
        return self.grid.update(step, density_fn, occ_threshold=threshold, ema_decay=cfg.occupancy_decay)

    def _density_for_grid(self, x: torch.Tensor) -> torch.Tensor:
        # The grid stores optical thickness of one step, as instant-ngp and nerfacc do. Its
        # refresh evaluates chunks of 2^18 cells, one more bucket for the graphed density pass,
        # with the last step's update applied first.
        self.phases.optimizer_update()
        return self.phases.density(x) * self.model.step_size

    def _render_batch(self, rays_o: torch.Tensor, rays_d: torch.Tensor) -> dict:
        """Render a training batch (stratified, no background: the loss blends it). With
        ``prune``, only the samples that composite go through the field with gradients: on CUDA
        packed into ``target_samples`` rows (fixed shapes, no extra sync), on the CPU (where a
        sync costs nothing) sized to fit. The last step's update is queued inside the march."""
        cfg, phases = self.config, self.phases
        capacity = self.target_samples if cfg.prune and self.device.type == "cuda" else None
        return self.model.render(
            rays_o, rays_d, phases.field, background=None, stratified=True,
            sigma_fn=phases.density if cfg.prune else None, sample_capacity=capacity,
            return_samples=cfg.distortion_weight > 0, before_sync=phases.optimizer_update,
            ray_images=self.batch_images, near_gradient_distance=cfg.near_gradient_distance)

    def step(self, progress: float = 0.0) -> dict:
        """One update on about ``target_samples`` samples, ``progress`` in [0, 1] through the
        budget (for the learning-rate schedule); returns ``loss`` ([] tensor), ``mse``,
        ``rays``, ``samples`` (trained on) and ``marched`` (host ints).

        The optimizer update of the gradients computed here is queued by the next step, while
        its march waits for the sample count, so that the GPU has work through that
        synchronisation; anything that reads the weights first calls :meth:`flush`."""
        t0 = time.perf_counter()
        cfg, phases = self.config, self.phases
        if not self.field.training:  # Module.train() walks every submodule: 27 µs a step
            self.field.train()
        with self.model.precision():  # the grid refresh shares the graphs of the density pass
            phases.grid_update(self.step_count, self._density_for_grid)
            rays_o, rays_d, target, background = phases.sample_batch(self.rays.n_rays)
            out = phases.render(rays_o, rays_d)
            dist = None
            if cfg.distortion_weight > 0 and out["n_samples"] > 0:
                near = self.model.march.near if cfg.distortion_spacing == "normalised" else 0.0
                dist = phases.distortion(out["weights"], out["t_starts"], out["t_ends"], out["ray_offsets"], near)
            # rays dropped for lack of room in the sample buffer (ray_mask) are left out
            # a pixel is the mean of its sub-rays, kept only if all of them are
            loss, mse = phases.loss(out["rgb"], out["opacity"], target, background,
                                    rays_kept(out.get("ray_mask"), self.batch_kept), dist,
                                    cfg.distortion_weight, huber_delta=0.1 if cfg.loss == "huber" else None,
                                    rays_per_pixel=cfg.supersample ** 2)
            self.weights.zero_grad()
            if self.camera_adam is not None:
                self.camera_adam.zero_grad(set_to_none=False)
            if out["n_samples"] > 0:
                phases.backward(loss)
                if self.camera_adam is not None:
                    self.camera_adam.step()
            if self.gradient_reduction is not None:  # every rank takes part, with samples or not
                self.gradient_reduction()
            if out["n_samples"] > 0 or self.gradient_reduction is not None:
                self.weights.defer(self.step_count, progress)
        n_samples = self.rays.samples_in_use(out)
        marched = out["n_marched"] if "n_marched" in out else n_samples  # host ints: no sync
        stats = {"loss": loss.detach(), "mse": mse, "rays": rays_o.shape[0], "samples": n_samples, "marched": marched}
        self.rays.adjust(n_samples)  # hold the sample count
        self.step_count += 1
        self.train_seconds += time.perf_counter() - t0
        return stats

    def flush(self) -> None:
        """Queue the optimizer update of the last step's gradients, if not done yet (see
        :meth:`step`): its learning rate and weight-average decay are the ones of that step."""
        self.phases.optimizer_update()

    def averaged_weights(self) -> list[torch.Tensor] | None:
        """The weight average, one tensor per field parameter in order, up to date (None
        without averaging)."""
        self.flush()
        return self.weights.averaged_weights()

    def train(self, show_progress: bool = True, checkpoint: Callable[[], None] | None = None,
              checkpoint_every: float = 300.0, stop: tuple[int | None, float | None] = (None, None),
              until: Callable[[], bool] | None = None, desc: str = "train") -> None:
        """Train until the step or time budget of the config is spent, with a progress bar on
        stderr named ``desc`` (loss, PSNR, rays and samples read every ``READOUT_EVERY`` steps,
        each readout a row of :attr:`curve`). Training seconds count the loop's own work between
        the steps too, not the checkpoints.

        The loss is copied to the host every ``READOUT_EVERY`` steps and read at the next
        readout, when the copy has landed (no wait for the GPU), and after the last step: a
        non-finite loss raises :class:`TrainingDiverged`, at most ``READOUT_EVERY`` steps late,
        and never after a checkpoint of the diverged field (a checkpoint reads its step's loss first).
        ``checkpoint`` (e.g. a save to disk), when given, is called at the first readout after
        each ``checkpoint_every`` seconds of wall-clock. ``stop`` (a step count, seconds of
        training; either None) ends it earlier, the schedule still running over the whole budget
        (a contraction probe's first steps), as does ``until`` returning True at a readout."""
        steps, seconds = self.config.budget()
        start_step, start_seconds = self.step_count, self.train_seconds
        stop_steps = None if stop[0] is None else stop[0] - start_step
        stop_seconds = None if stop[1] is None else stop[1] - start_seconds
        last_checkpoint = time.monotonic()
        # the bar counts steps, or seconds where only time ends the run (a time budget, no stop in steps alone)
        count_steps = steps is not None or (stop_steps is not None and stop_seconds is None)
        total = min(x for x in ((steps, stop_steps) if count_steps else (seconds, stop_seconds)) if x is not None)

        def done() -> float:  # at most the total: a time budget's last step ends past it
            return min(total, self.step_count - start_step if count_steps
                       else round(self.train_seconds - start_seconds, 1))

        with progress_bar(desc=desc, total=total, unit="step" if count_steps else "s", disable=not show_progress,
                          dynamic_ncols=True) as bar:
            try:
                while True:
                    began = time.perf_counter()
                    done_steps = self.step_count - start_step
                    clock = self.train_seconds if self.shared_clock is None else self.shared_clock(done_steps)
                    spent = clock - start_seconds
                    if any(limit is not None and used >= limit for used, limit in
                           ((done_steps, steps), (spent, seconds), (done_steps, stop_steps), (spent, stop_seconds))):
                        break
                    progress = max(self.step_count / (start_step + steps) if steps else 0.0,
                                   clock / (start_seconds + seconds) if seconds else 0.0)
                    stepping = time.perf_counter()
                    stats = self.step(progress)  # counts its own seconds
                    stepping, saving = time.perf_counter() - stepping, 0.0
                    readout = self.step_count % READOUT_EVERY == 0 or self.step_count == 1
                    if readout:
                        self._show_readout(bar if show_progress else None)  # the last readout's, landed by now
                        self._start_readout(stats)
                        if show_progress:
                            bar.update(done() - bar.n)
                        if checkpoint is not None and time.monotonic() - last_checkpoint >= checkpoint_every:
                            self._show_readout(bar if show_progress else None)  # never save a diverged field
                            saving = time.perf_counter()
                            checkpoint()
                            saving, last_checkpoint = time.perf_counter() - saving, time.monotonic()
                    # the loop's own work is training (0.1 s of a 15 s lego run on an H200), a checkpoint is not
                    self.train_seconds += time.perf_counter() - began - stepping - saving
                    if readout and until is not None and until():
                        break
            except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the pending readout joins the curve the caller saves
                self._show_readout(None)
                raise
            if self.step_count > start_step:  # the last step's loss, read once the GPU is done
                if not (self._readout.pending and self._readout_of["step"] == self.step_count):
                    self._show_readout(bar if show_progress else None)  # an earlier step's, still pending
                    self._start_readout(stats)
                self._show_readout(bar if show_progress else None)
            bar.update(done() - bar.n)
        self.flush()

    def _start_readout(self, stats: dict) -> None:
        """Queue the copy of a step's loss and mse (:meth:`step`'s ``stats``) to the host."""
        self._readout.start(stats["loss"], stats["mse"])
        self._readout_of = {"step": self.step_count, "seconds": self.train_seconds, "rays": stats["rays"],
                            "samples": stats["samples"]}

    def _show_readout(self, bar) -> None:
        """Read the queued readout, if any: check its loss and show it on ``bar`` (None: check only).

        Raises:
            TrainingDiverged: when the loss is not finite.
        """
        if not self._readout.pending:
            return
        (loss, mse), of = self._readout.read(), self._readout_of
        if not math.isfinite(loss):
            raise TrainingDiverged(f"training diverged: the loss is {loss} at step {of['step']} (try a lower lr)")
        psnr = self.record_readout(of["step"], of["seconds"], loss, mse, of["rays"], of["samples"])
        if bar is not None:
            bar.set_postfix(loss=f"{loss:.4f}", psnr=f"{psnr:.2f}", rays=of["rays"], samples=of["samples"],
                            refresh=False)

    def record_readout(self, step: int, seconds: float, loss: float, mse: float, rays: int, samples: int) -> float:
        """Keep one readout (a step's loss and mse read on the host) as a row of :attr:`curve`;
        returns its training PSNR."""
        psnr = -10.0 * math.log10(max(mse, 1e-10))
        self.curve.append((step, seconds, loss, psnr, rays, samples))
        return psnr

    # -- inference -------------------------------------------------------------------------
    @property
    def view_background(self) -> float | None:
        """What renders are composited over: white (1.0), or where the field learns the
        background (:attr:`black_background`) its environment (None, as
        :func:`~ngp_warp.outputs.renderer.render_view` takes it) or, for a field without one, black."""
        if not self.black_background:
            return 1.0
        return None if self.field.environment is not None else 0.0

    def training_c2w(self) -> torch.Tensor:
        """[N, 3, 4] float32 camera-to-world matrices of the training images as the field was
        fitted through them, on the trainer's device: with camera refinement the refined ones."""
        c2w = self.train_split.c2w
        return c2w if self.cameras is None else self.cameras.refined_c2w(c2w)

    def render_image(self, c2w: torch.Tensor, intrinsics: torch.Tensor, width: int, height: int,
                     distortion: torch.Tensor | None = None, background: float | None = 1.0, chunk: int | None = None,
                     spp: int = 1, fisheye: bool = False, supersample: int | None = None,
                     appearance_code: torch.Tensor | None = None,
                     other_codes: Sequence[torch.Tensor | None] = (),
                     first_round: int | str | None = "auto") -> dict:
        """:func:`ngp_warp.outputs.renderer.render_view` of one camera with the weight average (when
        on) and the training pixels' sub-pixel grid: [3, 4] c2w, [4] fx fy cx cy, optional [6]
        k1 k2 k3 k4 p1 p2 distortion (``fisheye``: OpenCV's fisheye lens) → rgb [H, W, 3],
        depth/opacity [H, W]. ``spp`` > 1 averages that many renders with jittered sample
        offsets along each ray; ``chunk`` None sizes the ray chunks to memory; ``supersample``
        overrides the sub-pixel grid (1: one ray per pixel, for previews); ``appearance_code``
        [A] float32 colours every ray (None: the mean training code); ``other_codes`` and
        ``first_round`` as in ``render_view``."""
        with self.weights.averaged_in_field():
            return render_view(self.model, c2w, intrinsics, width, height, distortion=distortion, fisheye=fisheye,
                               background=background, chunk=chunk, spp=spp,
                               supersample=supersample or self.config.supersample, appearance_code=appearance_code,
                               other_codes=other_codes, first_round=first_round)

    # -- state -----------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """Everything that resumes training: ``field``, ``grid``, the optimizer state
        (:meth:`FieldOptimizer.state_dict`), the ray count (:meth:`RayCount.state_dict`),
        ``step`` and ``train_seconds``: the keys of format-v1 checkpoints; ``curve``, :attr:`curve`
        as a [N, 6] float64 tensor. The settings are the constructor's. Applies the last step's
        update first."""
        self.flush()
        weights = self.weights.state_dict()
        cameras = {} if self.cameras is None else {"cameras": self.cameras.state_dict(),
                                                   "camera_adam": self.camera_adam.state_dict()}
        return {"field": self.field.state_dict(), "grid": self.grid.state_dict(), **weights, **cameras,
                **self.rays.state_dict(), "step": self.step_count, "train_seconds": self.train_seconds,
                "curve": torch.tensor(self.curve, dtype=torch.float64).reshape(-1, 6)}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` into a trainer built with the same settings (other keys
        are ignored)."""
        self.field.load_state_dict(state["field"])
        self.grid.load_state_dict(state["grid"])
        self.weights.load_state_dict(state)
        self.rays.load_state_dict(state)
        if self.cameras is not None and "cameras" in state:
            self.cameras.load_state_dict(state["cameras"])
            self.camera_adam.load_state_dict(state["camera_adam"])
        self.step_count = state["step"]
        self.train_seconds = state["train_seconds"]
        self.curve = [(int(r[0]), r[1], r[2], r[3], int(r[4]), int(r[5])) for r in state["curve"].tolist()] \
            if "curve" in state else []
