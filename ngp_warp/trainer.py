"""Per-scene training: sample rays across all training images, render, fit, keep the grid fresh."""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
from dataclasses import dataclass, field

import torch

from ngp_warp._checks import check_numbers
from ngp_warp.batch import sample_pixels
from ngp_warp.data import Scene, Split, generate_rays
from ngp_warp.field import INSTANT_NGP_FINEST_RESOLUTION, FieldConfig, NGPField
from ngp_warp.graphs import GraphedDensity
from ngp_warp.losses import distortion_loss_packed, ray_loss
from ngp_warp.occupancy import OccupancyGrid
from ngp_warp.optim import LazyAdam
from ngp_warp.progress import Progress
from ngp_warp.render import render_rays


@dataclass
class TrainConfig:
    """Training settings; ``None`` sizes pick a default for the device."""

    steps: int | None = None            # stop after this many steps ...
    seconds: float | None = None        # ... or after this much training wall-clock
    target_samples: int | None = None   # samples per batch to hold (2^18 CUDA, 2^15 CPU); with
                                        # prune, samples that composite (the rows trained on)
    initial_rays: int = 1024
    max_rays: int = 1 << 18
    lr: float = 1e-2
    weight_decay: float = 1e-6          # on MLP weights only
    loss: str = "l2"                    # "l2" or "huber"
    seed: int = 0
    grid_resolution: int = 128
    steps_per_diagonal: int = 1024      # marching step = finest cascade's diagonal / this
    cone_angle: float = 0.0
    early_stop_eps: float = 1e-4
    mlp_precision: str = "bf16"         # CUDA only (the CPU runs fp32): "bf16" autocast inside the
                                        # field's graphs, "tf32" matmuls, or "fp32"
    prune: bool = True                  # train only on samples that composite (no-grad σ pass first)
    cuda_graph: bool = True             # CUDA with prune: replay the field's forward/backward as graphs
    weight_average: float = 0.995       # > 0: render with an EMA of the weights, this decay per step
    lazy_table_adam: bool = True        # Adam skips hash-table entries with zero gradient (tiny-cuda-nn),
                                        # and keeps their weight average in the same pass
    supersample: int | None = None      # > 1: each training pixel is the mean of supersample² rays on
                                        # a sub-pixel grid (as the images were area-downsampled), and
                                        # renders average the same grid; None: 2 on CUDA, 1 on the CPU
    distortion_weight: float = 0.0      # weight of the mean distortion loss per ray (t in world units)
    field: FieldConfig = field(default_factory=FieldConfig)

    def check(self) -> None:
        """Raise ValueError naming the first setting outside its range (None is left to the
        device), the field's sizes included."""
        choices = {"loss": ("l2", "huber"), "mlp_precision": ("fp32", "tf32", "bf16"), "supersample": (None, 1, 2, 3, 4)}
        for name, allowed in choices.items():
            value = getattr(self, name)
            if value not in allowed or type(value) not in (str, int, type(None)):
                raise ValueError(f"{name} must be one of {', '.join(map(str, allowed))}, got {value!r}")
        check_numbers(self, counts=("steps", "target_samples", "initial_rays", "max_rays", "grid_resolution",
                                     "steps_per_diagonal"),
                       positive=("seconds", "lr"),
                       non_negative=("weight_decay", "cone_angle", "early_stop_eps", "distortion_weight"),
                       optional=("steps", "seconds", "target_samples"))
        if not 0.0 <= self.weight_average < 1.0:
            raise ValueError(f"weight_average must be in [0, 1), got {self.weight_average!r}")
        self.field.check()

    def budget(self) -> tuple[int | None, float | None]:
        if self.steps is None and self.seconds is None:
            return 20000, None
        return self.steps, self.seconds


def apply_overrides(config: TrainConfig, settings: list[str]) -> TrainConfig:
    """A copy of ``config`` with ``key=value`` settings applied (``field.key`` for the field's
    sizes); values take the setting's declared type (``none`` for settings that default to
    None, e.g. ``field.finest_resolution``). Raises ValueError on unknown keys or values that do
    not parse."""
    config = dataclasses.replace(config, field=dataclasses.replace(config.field))
    for item in settings:
        key, sep, text = item.partition("=")
        target, name = (config.field, key[6:]) if key.startswith("field.") else (config, key)
        names = {f.name for f in dataclasses.fields(target)} - {"field"}
        if not sep or name not in names:
            raise ValueError(f"unknown setting {item!r}; expected key=value with key one of "
                             f"{', '.join(sorted(names | {'field.' + n for n in _field_names()}))}")
        declared = {f.name: f for f in dataclasses.fields(target)}[name]
        optional = declared.default is None
        value = None if optional and text.lower() == "none" else _parse_value(declared.type, text, key)
        setattr(target, name, value)
    return config


def _field_names() -> list[str]:
    return [f.name for f in dataclasses.fields(FieldConfig)]


def _parse_value(declared: str, text: str, key: str):
    """``text`` as the dataclass field's declared type (an annotation string such as
    ``"float | None"``: this module postpones annotations)."""
    kind = declared.split("|")[0].strip()
    if kind == "bool":
        if text.lower() not in ("true", "false", "1", "0"):
            raise ValueError(f"{key} takes true or false, got {text!r}")
        return text.lower() in ("true", "1")
    if kind == "str":
        return text
    try:
        return int(text) if kind == "int" else float(text)
    except ValueError:
        raise ValueError(f"{key} takes {'an integer' if kind == 'int' else 'a number'}, got {text!r}") from None


def pixel_matched_resolution(scene: Scene, subpixels: int = 1) -> float:
    """The finest hash-grid resolution whose cells are about one training pixel wide at the
    field box's centre: the box's longest side over the median pixel footprint (camera distance
    to the centre over the focal length fx), rounded, clamped to [64, 2048 per unit cube]
    (instant-ngp's 2048 × aabb_scale). Training on ``subpixels``² rays per pixel makes the cells
    √subpixels times finer.

    On lego at 400×400 this gives 413 cells. Measured there after 60 s (RESULTS.md): finest
    256 / 362 / 512 / 724 / 1024 / 2048 give 34.97 / 35.31 / 35.25 / 35.03 / 34.74 / 34.43 dB:
    levels finer than the pixels let the field fit each training ray on its own, which the test
    views do not share. With 2×2 sub-rays per pixel (H200, 300 s, 25 views) finest 413 / 584 /
    826 gave 36.67 / 36.84 / 36.70 dB, and with 3×3, 716 against 1239 cells gave 36.95 against
    36.76 dB: the sub-rays resolve detail finer than a pixel, but not a full sub-pixel's worth.
    """
    split = scene.train
    box = scene.aabb.double()
    centre = 0.5 * (box[:3] + box[3:])
    distance = (split.c2w[:, :, 3].double() - centre).norm(dim=-1)
    footprint = float((distance / split.intrinsics[:, 0].double()).median()) / math.sqrt(subpixels)
    side = float((box[3:] - box[:3]).max())
    unit = float((scene.occupancy_aabb[3:] - scene.occupancy_aabb[:3]).max())
    ceiling = INSTANT_NGP_FINEST_RESOLUTION * side / unit
    return float(min(max(round(side / max(footprint, 1e-12)), 64), ceiling))


def device_defaults(config: TrainConfig, device_type: str) -> TrainConfig:
    """``config`` with ``supersample`` filled in when left to None: 2×2 sub-rays per training
    pixel on CUDA, one ray on the CPU.

    On lego (H200, schedule over 300 s, 200 views, RESULTS.md) the sub-rays took the 300 s PSNR
    from 34.75 to 36.61 dB. With them, session 8's 2^21-entry table and distortion loss no longer
    helped (36.67–36.74 dB at 300 s with or without them, 25 views; NOTES entry 21), so the table
    is instant-ngp's 2^19 and the distortion loss is off by default on both devices. On the CPU,
    2×2 sub-rays gave 33.18 against 33.56 dB on the demo in 150 s on 2 cores.
    """
    if config.supersample is not None:
        return config
    return dataclasses.replace(config, supersample=2 if device_type == "cuda" else 1)


def default_device() -> str:
    """``cuda`` when torch and Warp both see a GPU, else ``cpu``."""
    from ngp_warp import _wp

    return "cuda" if _wp.cuda_available() else "cpu"


def composite_on(rgba: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """[..., 3|4] uint8 pixels → [..., 3] float in [0, 1], alpha blended over ``background``."""
    px = rgba.float() / 255.0
    if px.shape[-1] == 3:
        return px
    a = px[..., 3:]
    return px[..., :3] * a + background * (1.0 - a)


class _FieldForward(torch.nn.Module):
    """The field's forward as its own module (its parameters are the field's)."""

    def __init__(self, field: NGPField):
        super().__init__()
        self.field = field

    def forward(self, positions: torch.Tensor, directions: torch.Tensor):
        return self.field(positions, directions)


class Trainer:
    """Holds the field, occupancy grid and optimizer of one scene; :meth:`step` is one update."""

    def __init__(self, scene: Scene, config: TrainConfig | None = None, device: str | None = None):
        self.config = cfg = config or TrainConfig()
        cfg.check()
        self.device = torch.device(device or default_device())
        # settings left to None are resolved here, so checkpoints store the numbers used
        cfg = self.config = device_defaults(cfg, self.device.type)
        if cfg.field.finest_resolution is None:
            cfg = self.config = dataclasses.replace(cfg, field=dataclasses.replace(
                cfg.field, finest_resolution=pixel_matched_resolution(scene, cfg.supersample)))
        torch.manual_seed(cfg.seed)
        self.scene = scene
        self.train_split: Split = scene.train.to(self.device)
        aabb = scene.aabb.to(self.device)
        self.field = NGPField(aabb, cfg.field).to(self.device)
        self.grid = OccupancyGrid(scene.occupancy_aabb, resolution=cfg.grid_resolution,
                                  levels=scene.occupancy_levels).to(self.device)
        # Step on the finest cascade's scale (instant-ngp's √3/1024 of its unit cube), not the
        # whole field box, which is aabb_scale times larger for instant-ngp scenes.
        box = scene.occupancy_aabb
        self.step_size = float((box[3:] - box[:3]).norm()) / cfg.steps_per_diagonal
        self.target_samples = cfg.target_samples or (1 << 18 if self.device.type == "cuda" else 1 << 15)
        self.n_rays = cfg.initial_rays
        table = {"params": list(self.field.encoding.parameters()), "weight_decay": 0.0}
        mlp = {"params": self.field.mlp_parameters(), "weight_decay": cfg.weight_decay}
        self.optimizer = torch.optim.Adam(
            [mlp] if cfg.lazy_table_adam else [table, mlp], lr=cfg.lr, betas=(0.9, 0.99), eps=1e-15,
            fused=self.device.type == "cuda",  # one kernel for the whole update on the GPU
        )
        self.table_optimizer = (LazyAdam(table["params"], lr=cfg.lr, betas=(0.9, 0.99), eps=1e-15)
                                if cfg.lazy_table_adam else None)
        self.step_count = 0
        self.train_seconds = 0.0
        self._contributing_host: torch.Tensor | None = None  # pinned copy of the last step's count
        self._marched_before = 0
        self._fraction = 1.0  # contributing / marched samples, from the step before
        self._pending_update: tuple[float, float | None] | None = None  # (lr, decay), see step
        self._graphed_field = None  # captured on first use (see field_fn)
        self._graphed_density = None  # likewise (see _sigma_fn)
        # Exponential moving average of the weights, used for rendering when enabled. The lazy
        # table optimizer keeps the table's; the rest are lerped after each step.
        self._params = list(self.field.parameters())
        self.averaged = [p.detach().clone() for p in self._params] if cfg.weight_average > 0 else None
        self._lerped: tuple[list[torch.Tensor], list[torch.Tensor]] = ([], [])
        for p, average in zip(self._params, self.averaged or []):
            if self.table_optimizer is not None and any(p is q for q in table["params"]):
                self.table_optimizer.keep_average(p, average)
            else:
                self._lerped[0].append(average)
                self._lerped[1].append(p.detach())  # shares the storage; keeps the lerp out of autograd
        self.grid.mark_invisible_cells(
            self.train_split.c2w, self.train_split.intrinsics, self.train_split.width, self.train_split.height
        )

    # -- one optimisation step -------------------------------------------------------------
    def optimizers(self) -> list[torch.optim.Optimizer]:
        """The MLP's Adam (and the table's, unless the table has its own LazyAdam)."""
        return [self.optimizer] if self.table_optimizer is None else [self.optimizer, self.table_optimizer]

    def _lr_factor(self, progress: float) -> float:
        """Linear warm-up over 100 steps, then ×0.33 at 50 %, 75 % and 90 % of the budget."""
        warm = min(1.0, 0.01 + self.step_count / 100.0)
        return warm * 0.33 ** sum(progress >= m for m in (0.5, 0.75, 0.9))

    def _density_for_grid(self, x: torch.Tensor) -> torch.Tensor:
        # The grid stores optical thickness of one step, as instant-ngp and nerfacc do. Its
        # refresh evaluates chunks of 2^18 cells, one more bucket for the graphed density pass,
        # with the last step's update applied first.
        self.flush()
        return self._sigma_fn()(x) * self.step_size

    def field_fn(self, positions: torch.Tensor, directions: torch.Tensor):
        """The field; in CUDA training with pruning, its forward and backward replay CUDA graphs
        captured for the fixed ``target_samples`` rows (one launch each instead of ~70)."""
        if self.field.training and positions.shape[0] == self.target_samples and self._graphs_apply():
            if self._graphed_field is None:
                # The capture's warm-up runs on a side stream, so autograd would warn that the
                # parameters' gradients arrive from another stream; that is expected here.
                quiet = getattr(torch.autograd.graph, "set_warn_on_accumulate_grad_stream_mismatch", None)
                if quiet is not None:
                    quiet(False)
                # Capture a wrapper: make_graphed_callables replaces the captured module's
                # forward, and the field itself must stay callable at any size.
                self._graphed_field = torch.cuda.make_graphed_callables(
                    _FieldForward(self.field), (positions.detach().clone(), directions.detach().clone()))
            return self._graphed_field(positions, directions)
        return self.field(positions, directions)

    def _sigma_fn(self):
        """The no-gradient density pass (before pruning, and for the grid refresh): in CUDA
        training with graphs, replayed per bucket of sample counts (see
        :class:`ngp_warp.graphs.GraphedDensity`)."""
        if not self._graphs_apply():
            return self.field.density
        if self._graphed_density is None:
            self._graphed_density = GraphedDensity(self.field.density)
        return self._graphed_density

    def _graphs_apply(self) -> bool:
        cfg = self.config
        return cfg.cuda_graph and cfg.prune and self.device.type == "cuda"

    @contextlib.contextmanager
    def _mlp_precision(self):
        """The MLPs' matmul precision on CUDA (master weights stay float32). bf16 autocast runs
        without its cast cache, which CUDA-graph capture requires: the weights' casts are then
        part of the captured graphs (a few kernels over 13 k weights)."""
        mode = self.config.mlp_precision
        if self.device.type != "cuda" or mode == "fp32":
            yield
        elif mode == "bf16":
            with torch.autocast("cuda", dtype=torch.bfloat16, cache_enabled=False):
                yield
        else:  # tf32 (the constructor checked the mode)
            saved = torch.backends.cuda.matmul.allow_tf32
            torch.backends.cuda.matmul.allow_tf32 = True
            try:
                yield
            finally:
                torch.backends.cuda.matmul.allow_tf32 = saved

    def render(self, rays_o, rays_d, background, stratified: bool) -> dict:
        """Render rays. In training with ``prune``, only the samples that composite go through
        the field with gradients: on CUDA packed into ``target_samples`` rows (fixed shapes, no
        extra sync), on the CPU (where a sync costs nothing) sized to fit."""
        prune = self.config.prune and self.field.training
        capacity = self.target_samples if prune and self.device.type == "cuda" else None
        return render_rays(
            rays_o, rays_d, self.grid, self.field_fn,
            near=self.scene.near, far=1e4, step_size=self.step_size,
            cone_angle=self.config.cone_angle, early_stop_eps=self.config.early_stop_eps,
            background=background, stratified=stratified,
            sigma_fn=self._sigma_fn() if prune else None, sample_capacity=capacity,
            return_samples=self.field.training and self.config.distortion_weight > 0,
            before_sync=self.flush if self.field.training else None,
        )

    def sample_batch(self, n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Rays through random pixels across all training images → (rays_o, rays_d [p k, 3],
        target rgb and background [p, 3] per pixel) for p = max(1, n div k) pixels of k =
        supersample² rays each, drawn in one launch from a seed that mixes the config's seed
        with the step count."""
        seed = (self.step_count * 0x9E3779B1 + self.config.seed * 0x85EBCA6B) & 0x7FFFFFFF
        sub = self.config.supersample
        b = sample_pixels(self.train_split, max(1, n // (sub * sub)), seed, sub)
        return b.rays_o, b.rays_d, b.target, b.background

    def step(self, progress: float = 0.0) -> dict:
        """One update on about ``target_samples`` samples; returns loss, PSNR, rays, samples.

        The optimizer update of the gradients computed here is queued by the next step, while
        its march waits for the sample count, so that the GPU has work through that
        synchronisation; anything that reads the weights first calls :meth:`flush`."""
        t0 = time.perf_counter()
        update = (self.config.lr * self._lr_factor(progress), self._average_decay())
        if not self.field.training:  # Module.train() walks every submodule: 27 µs a step
            self.field.train()
        with self._mlp_precision():  # the grid refresh shares the graphs of the density pass
            self.grid.update(self.step_count, self._density_for_grid)
            rays_o, rays_d, target, background = self.sample_batch(self.n_rays)
            out = self.render(rays_o, rays_d, None, stratified=True)  # the loss blends the background
            weight = self.config.distortion_weight
            dist = None
            if weight > 0 and out["n_samples"] > 0:
                dist = distortion_loss_packed(out["weights"], out["t_starts"], out["t_ends"], out["ray_offsets"])
            # rays dropped for lack of room in the sample buffer (ray_mask) are left out
            # a pixel is the mean of its sub-rays, kept only if all of them are
            loss, mse = ray_loss(out["rgb"], out["opacity"], target, background, out.get("ray_mask"), dist, weight,
                                 huber_delta=0.1 if self.config.loss == "huber" else None,
                                 rays_per_pixel=self.config.supersample ** 2)
            for p in self._params:  # what zero_grad(set_to_none=True) does, at a 20th of its host time
                p.grad = None
            if out["n_samples"] > 0:
                # On the calling thread: handing the backward to autograd's CUDA worker thread
                # and back cost 0.45 ms of host time per step (H200, 2^16 rows: 2.20 → 1.76 ms).
                with torch.autograd.set_multithreading_enabled(False):
                    loss.backward()
                self._pending_update = update
        n_samples = self._samples_in_use(out)
        marched = out["n_marched"] if "n_marched" in out else n_samples  # host ints: no sync
        stats = {"loss": loss.detach(), "mse": mse, "rays": rays_o.shape[0], "samples": n_samples, "marched": marched}
        # Hold the sample count: scale the ray count by target / actual (smoothed, clamped).
        ratio = self.target_samples / max(n_samples, 1)
        new = self.n_rays * min(max(ratio, 0.5), 2.0) ** 0.5
        self.n_rays = int(min(max(256, round(new / 128) * 128), self.config.max_rays))
        self.step_count += 1
        self.train_seconds += time.perf_counter() - t0
        return stats

    def flush(self) -> None:
        """Queue the optimizer update of the last step's gradients, if not done yet (see
        :meth:`step`): its learning rate and weight-average decay are the ones of that step."""
        if self._pending_update is None:
            return
        lr, decay = self._pending_update
        self._pending_update = None
        for opt in self.optimizers():
            for group in opt.param_groups:
                group["lr"] = lr
        if self.table_optimizer is not None:
            self.table_optimizer.param_groups[0]["average_decay"] = decay
        for opt in self.optimizers():
            opt.step()
        if self._lerped[0]:
            torch._foreach_lerp_(self._lerped[0], self._lerped[1], 1.0 - decay)

    def _samples_in_use(self, out: dict) -> int:
        """The sample count the ray count is steered by. Without pruning, the marched count.
        With it, the contributing count (before the capacity cut, so it may exceed it; the
        rays past the capacity are dropped): reading it would sync, so it is estimated as the
        marched count times the previous step's contributing fraction (read from a copy that
        has long finished: this step's march synchronised after it)."""
        if "n_marched" not in out:
            return int(out["n_samples"])
        marched = out["n_marched"]
        if self._contributing_host is None:
            pin = self.device.type == "cuda"
            self._contributing_host = torch.zeros(1, dtype=torch.int32, pin_memory=pin)
        elif self._marched_before > 0:  # the previous step's copy is done: this step's march synced
            self._fraction = min(1.0, int(self._contributing_host) / self._marched_before)
        self._contributing_host.copy_(out["n_contributing"], non_blocking=True)
        self._marched_before = marched
        return int(marched * self._fraction)

    def _average_decay(self) -> float | None:
        """This step's weight-average decay (None without averaging): a short memory early on,
        so the random initial weights wash out quickly."""
        if self.averaged is None:
            return None
        return min(self.config.weight_average, (1 + self.step_count) / (10 + self.step_count))

    def averaged_weights(self) -> list[torch.Tensor] | None:
        """The weight average, one tensor per field parameter in order, up to date (None
        without averaging)."""
        self.flush()
        if self.averaged is not None and self.table_optimizer is not None:
            self.table_optimizer.flush_averages()
        return self.averaged

    @contextlib.contextmanager
    def _render_weights(self):
        """The averaged weights in the field while rendering (when averaging is on); either way
        the last step's update is applied first (by :meth:`averaged_weights`)."""
        averaged = self.averaged_weights()
        if averaged is None:
            yield
            return
        params = [p.data for p in self.field.parameters()]
        live = [p.clone() for p in params]
        torch._foreach_copy_(params, averaged)
        try:
            yield
        finally:
            torch._foreach_copy_(params, live)

    def train(self, show_progress: bool = True) -> None:
        """Train until the step or time budget of the config is spent."""
        steps, seconds = self.config.budget()
        bar = Progress("train", total=steps, seconds=seconds, enabled=show_progress)
        start_step, start_seconds = self.step_count, self.train_seconds
        while True:
            done_steps = self.step_count - start_step
            spent = self.train_seconds - start_seconds
            if (steps is not None and done_steps >= steps) or (seconds is not None and spent >= seconds):
                break
            progress = max(self.step_count / (start_step + steps) if steps else 0.0,
                           self.train_seconds / (start_seconds + seconds) if seconds else 0.0)
            stats = self.step(progress)
            if bar.enabled and (self.step_count % 10 == 0 or self.step_count == 1):
                psnr = -10.0 * math.log10(max(float(stats["mse"]), 1e-10))
                bar.update(done_steps + 1, loss=f"{float(stats['loss']):.4f}", psnr=f"{psnr:.2f}",
                           rays=stats["rays"], samples=stats["samples"])
        self.flush()
        bar.close()

    # -- inference -------------------------------------------------------------------------
    @torch.no_grad()
    def render_image(self, c2w, intrinsics, width: int, height: int, distortion=None,
                     background: float = 1.0, chunk: int = 1 << 14, spp: int = 1) -> dict:
        """Render one camera ([3, 4] c2w, [4] fx fy cx cy, optional [4] k1 k2 p1 p2 distortion;
        None skips undistortion) → rgb [H, W, 3], depth/opacity [H, W]. ``spp`` > 1 averages
        that many renders with jittered sample offsets along each ray."""
        if not (isinstance(spp, int) and spp >= 1):
            raise ValueError(f"spp must be a positive integer, got {spp!r}")
        self.field.eval()
        with self._render_weights():
            return self._render_image(c2w, intrinsics, width, height, distortion, background, chunk, spp)

    def _render_image(self, c2w, intrinsics, width, height, distortion, background, chunk, spp) -> dict:
        dev = self.device
        ys, xs = torch.meshgrid(torch.arange(height, device=dev), torch.arange(width, device=dev), indexing="ij")
        px, py = xs.reshape(-1), ys.reshape(-1)
        n = px.numel()
        c2w = c2w.to(dev).expand(n, 3, 4)
        intr = intrinsics.to(dev).expand(n, 4)
        dist = None if distortion is None else distortion.to(dev).expand(n, 4)
        bg = torch.full((3,), float(background), device=dev)
        parts = {"rgb": [], "depth": [], "opacity": []}
        sub = self.config.supersample  # the training pixels' sub-pixel grid, offsets from the centre
        shifts = [((a + 0.5) / sub - 0.5, (b + 0.5) / sub - 0.5) for b in range(sub) for a in range(sub)]
        for lo in range(0, n, chunk):
            hi = min(n, lo + chunk)
            sums = dict.fromkeys(parts, 0.0)  # running sums: memory stays one render's whatever sub and spp
            for dx, dy in shifts:
                rays_o, rays_d = generate_rays(c2w[lo:hi], intr[lo:hi], None if dist is None else dist[lo:hi],
                                               px[lo:hi] + dx, py[lo:hi] + dy)
                for _ in range(spp):
                    with self._mlp_precision():
                        out = self.render(rays_o, rays_d, bg, stratified=spp > 1)
                    for k in parts:
                        sums[k] = sums[k] + out[k].float()
            for k in parts:
                parts[k].append(sums[k] / (len(shifts) * spp))
        return {
            "rgb": torch.cat(parts["rgb"]).reshape(height, width, 3).clamp(0, 1),
            "depth": torch.cat(parts["depth"]).reshape(height, width),
            "opacity": torch.cat(parts["opacity"]).reshape(height, width),
        }
