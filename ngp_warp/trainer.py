"""Per-scene training: sample rays across all training images, render, fit, keep the grid fresh."""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from ngp_warp.data import Scene, Split, generate_rays
from ngp_warp.field import FieldConfig, NGPField
from ngp_warp.occupancy import OccupancyGrid
from ngp_warp.progress import Progress
from ngp_warp.render import render_rays


@dataclass
class TrainConfig:
    """Training settings; ``None`` sizes pick a default for the device."""

    steps: int | None = None            # stop after this many steps ...
    seconds: float | None = None        # ... or after this much training wall-clock
    target_samples: int | None = None   # samples per batch to hold (2^18 CUDA, 2^15 CPU)
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
    mlp_precision: str = "fp32"         # CUDA only: "fp32", "tf32" matmuls, or "bf16" autocast
    field: FieldConfig = field(default_factory=FieldConfig)

    def budget(self) -> tuple[int | None, float | None]:
        if self.steps is None and self.seconds is None:
            return 20000, None
        return self.steps, self.seconds


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


class Trainer:
    """Holds the field, occupancy grid and optimizer of one scene; :meth:`step` is one update."""

    def __init__(self, scene: Scene, config: TrainConfig | None = None, device: str | None = None):
        self.config = cfg = config or TrainConfig()
        self.device = torch.device(device or default_device())
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
        self.optimizer = torch.optim.Adam(
            [
                {"params": self.field.encoding.parameters(), "weight_decay": 0.0},
                {"params": self.field.mlp_parameters(), "weight_decay": cfg.weight_decay},
            ],
            lr=cfg.lr, betas=(0.9, 0.99), eps=1e-15,
            fused=self.device.type == "cuda",  # one kernel for the whole update on the GPU
        )
        self.step_count = 0
        self.train_seconds = 0.0
        self.grid.mark_invisible_cells(
            self.train_split.c2w, self.train_split.intrinsics, self.train_split.width, self.train_split.height
        )

    # -- one optimisation step -------------------------------------------------------------
    def _lr_factor(self, progress: float) -> float:
        """Linear warm-up over 100 steps, then ×0.33 at 50 %, 75 % and 90 % of the budget."""
        warm = min(1.0, 0.01 + self.step_count / 100.0)
        return warm * 0.33 ** sum(progress >= m for m in (0.5, 0.75, 0.9))

    def _density_for_grid(self, x: torch.Tensor) -> torch.Tensor:
        # The grid stores optical thickness of one step, as instant-ngp and nerfacc do.
        return self.field.density(x) * self.step_size

    def field_fn(self, positions: torch.Tensor, directions: torch.Tensor):
        return self.field(positions, directions)

    @contextlib.contextmanager
    def _mlp_precision(self):
        """The MLPs' matmul precision on CUDA (master weights stay float32)."""
        mode = self.config.mlp_precision
        if self.device.type != "cuda" or mode == "fp32":
            yield
        elif mode == "bf16":
            with torch.autocast("cuda", dtype=torch.bfloat16):
                yield
        elif mode == "tf32":
            saved = torch.backends.cuda.matmul.allow_tf32
            torch.backends.cuda.matmul.allow_tf32 = True
            try:
                yield
            finally:
                torch.backends.cuda.matmul.allow_tf32 = saved
        else:
            raise ValueError(f"mlp_precision must be fp32, tf32 or bf16, got {mode!r}")

    def render(self, rays_o, rays_d, background, stratified: bool) -> dict:
        return render_rays(
            rays_o, rays_d, self.grid, self.field_fn,
            near=self.scene.near, far=1e4, step_size=self.step_size,
            cone_angle=self.config.cone_angle, early_stop_eps=self.config.early_stop_eps,
            background=background, stratified=stratified,
        )

    def sample_batch(self, n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Random pixels across all training images → (rays_o, rays_d, target rgb, background)."""
        s = self.train_split
        dev = self.device
        img = torch.randint(0, s.images.shape[0], (n,), device=dev)
        px = torch.randint(0, s.width, (n,), device=dev)
        py = torch.randint(0, s.height, (n,), device=dev)
        rays_o, rays_d = s.rays(img, px, py)
        background = torch.rand(n, 3, device=dev) if s.images.shape[-1] == 4 else torch.ones(n, 3, device=dev)
        target = composite_on(s.images[img, py, px], background)
        return rays_o, rays_d, target, background

    def step(self, progress: float = 0.0) -> dict:
        """One update on about ``target_samples`` samples; returns loss, PSNR, rays, samples."""
        t0 = time.perf_counter()
        for group in self.optimizer.param_groups:
            group["lr"] = self.config.lr * self._lr_factor(progress)
        self.field.train()
        self.grid.update(self.step_count, self._density_for_grid)
        rays_o, rays_d, target, background = self.sample_batch(self.n_rays)
        with self._mlp_precision():
            out = self.render(rays_o, rays_d, background, stratified=True)
            n_samples = int(out["n_samples"])
            if self.config.loss == "huber":
                loss = F.huber_loss(out["rgb"], target, delta=0.1)
            else:
                loss = F.mse_loss(out["rgb"], target)
            self.optimizer.zero_grad(set_to_none=True)
            if n_samples > 0:
                loss.backward()
                self.optimizer.step()
        mse = F.mse_loss(out["rgb"].detach(), target)
        stats = {"loss": loss.detach(), "mse": mse, "rays": self.n_rays, "samples": n_samples}
        # Hold the sample count: scale the ray count by target / actual (smoothed, clamped).
        ratio = self.target_samples / max(n_samples, 1)
        new = self.n_rays * min(max(ratio, 0.5), 2.0) ** 0.5
        self.n_rays = int(min(max(256, round(new / 256) * 256), self.config.max_rays))
        self.step_count += 1
        self.train_seconds += time.perf_counter() - t0
        return stats

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
        bar.close()

    # -- inference -------------------------------------------------------------------------
    @torch.no_grad()
    def render_image(self, c2w, intrinsics, width: int, height: int, distortion=None,
                     background: float = 1.0, chunk: int = 1 << 14) -> dict:
        """Render one camera ([3, 4] c2w, [4] fx fy cx cy, optional [4] k1 k2 p1 p2 distortion;
        None skips undistortion) → rgb [H, W, 3], depth/opacity [H, W]."""
        self.field.eval()
        dev = self.device
        ys, xs = torch.meshgrid(torch.arange(height, device=dev), torch.arange(width, device=dev), indexing="ij")
        px, py = xs.reshape(-1), ys.reshape(-1)
        n = px.numel()
        c2w = c2w.to(dev).expand(n, 3, 4)
        intr = intrinsics.to(dev).expand(n, 4)
        dist = None if distortion is None else distortion.to(dev).expand(n, 4)
        bg = torch.full((3,), float(background), device=dev)
        parts = {"rgb": [], "depth": [], "opacity": []}
        for lo in range(0, n, chunk):
            hi = min(n, lo + chunk)
            rays_o, rays_d = generate_rays(c2w[lo:hi], intr[lo:hi], None if dist is None else dist[lo:hi],
                                           px[lo:hi], py[lo:hi])
            with self._mlp_precision():
                out = self.render(rays_o, rays_d, bg, stratified=False)
            for k in parts:
                parts[k].append(out[k].float())
        return {
            "rgb": torch.cat(parts["rgb"]).reshape(height, width, 3).clamp(0, 1),
            "depth": torch.cat(parts["depth"]).reshape(height, width),
            "opacity": torch.cat(parts["opacity"]).reshape(height, width),
        }
