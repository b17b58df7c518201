"""The built-in scenes of ``ngp-warp demo``: their training settings and generators."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from ngp_warp.training.config import TrainConfig, cpu_sizes
from ngp_warp.data.scene import write_demo_scene
from ngp_warp.data.scene_unbounded import write_unbounded_scene


def demo_config(device: str, steps: int | None, seconds: float | None, seed: int):
    """Training settings for the 100×100 demo scene. On the CPU a smaller table, a coarser
    occupancy grid and a longer step keep 2 cores busy on useful samples; the finest hash-grid
    level follows the images (104 cells here; measured on 2 cores after 150 s: 33.8 dB, against
    32.7 dB with 512 cells, see benchmarks/RESULTS.md)."""
    if steps is None and seconds is None:
        seconds = 150.0 if device == "cpu" else 30.0
    if device == "cpu":
        return cpu_sizes(TrainConfig(steps=steps, seconds=seconds, seed=seed, target_samples=1 << 13,
                                     steps_per_diagonal=512))
    return TrainConfig(steps=steps, seconds=seconds, seed=seed)


def unbounded_demo_config(device: str, steps: int | None, seconds: float | None, seed: int):
    """Training settings for the unbounded demo scene (100×100, 60 views; contraction, cone steps
    and appearance codes are the scene's defaults). On the CPU as :func:`demo_config`, with a
    step of 1/128 of the contracted grid's diagonal (0.22 world units inside the inner box; about
    40 samples per ray, so that 2 cores train on a few hundred rays per step)."""
    config = demo_config(device, steps, seconds, seed)
    if device == "cpu":
        config.steps_per_diagonal = 128
    return config


@dataclass(frozen=True)
class Demo:
    """One built-in scene: its settings for a device and budget, the folder it is generated into
    (inside the run's output folder) and its generator."""

    config: Callable[[str, int | None, float | None, int], TrainConfig]
    folder: str
    write: Callable[..., object]
    pixels: int = 100  # the images' width and height, as ``write`` renders them by default


DEMOS = {
    "demo": Demo(demo_config, "scene", write_demo_scene),
    "unbounded": Demo(unbounded_demo_config, "scene-unbounded", write_unbounded_scene),
}
