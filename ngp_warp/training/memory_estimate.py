"""What a training configuration needs in memory, estimated before anything is allocated.

Three parts dominate, each an upper bound of its first use:

* the occupancy grid: ``levels × resolution³`` cells of a float32 density, a float32 splat
  buffer and a bit (9 bytes a cell with the mips, rounded up);
* the hash tables: ``n_levels × 2^log2_hashmap_size × features`` float32 parameters, with their
  gradient, two Adam moments and the weight average (5 copies), and likewise the MLPs' weights
  and the appearance codes;
* the first batch's march: before the grid has learnt anything every cell is occupied, so each
  of ``initial_rays`` rays takes every step across the coarsest cascade's box (its diagonal over
  the step, fewer with cone steps), and every marched sample costs its interval, position and
  direction (40 bytes) plus the density pass over it (~360 bytes at the default widths: the
  encoding's L × F outputs and the MLP's hidden units; ~1.5 KB with the gradient graph when
  nothing is pruned), scaled by the field's widths.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import torch

from ngp_warp.ops.field import FieldConfig

GRID_BYTES_PER_CELL = 9
TABLE_COPIES = 5
MARCH_BYTES_PER_SAMPLE = 40
FIELD_BYTES_PER_SAMPLE = {True: 360, False: 1500}  # prune (no-grad density pass) or not
MAX_SAMPLES_PER_CALL = (2**31 - 1) // 16  # the hash grid indexes [N, levels] items with int32


class SettingsTooLarge(ValueError):
    """Settings that cannot fit in the device's memory; the message is one line."""


@dataclass(frozen=True)
class MemoryEstimate:
    """Bytes each part needs (see the module docstring) and the first batch's sample bound."""

    grid_cells: int
    grid_bytes: int
    table_bytes: int
    mlp_bytes: int
    first_batch_samples: int
    march_bytes: int

    @property
    def total(self) -> int:
        return self.grid_bytes + self.table_bytes + self.mlp_bytes + self.march_bytes


def mlp_parameters(field, n_images: int) -> int:
    """Weights of a :class:`~ngp_warp.ops.field.FieldConfig`'s density and colour MLPs (as
    :class:`~ngp_warp.ops.field.NGPField` builds them) and its ``n_images`` appearance codes."""
    codes = field.appearance_dim or 0
    density = (field.n_levels * field.n_features_per_level + 1) * field.hidden + (field.hidden + 1) * field.geo_features
    colour = (field.geo_features + 16 + codes + 1) * field.hidden + (field.hidden + 1) * (field.hidden + 3)
    return density + colour + n_images * codes


def sample_width(field) -> int:
    """Floats one sample holds through the field: encoding, hidden units, geometry and colour inputs."""
    codes = field.appearance_dim or 0
    return field.n_levels * field.n_features_per_level + 3 * field.hidden + field.geo_features * 2 + 16 + codes + 3


def samples_per_ray(length: float, step: float, cone_angle: float, max_step: float) -> float:
    """Steps a ray takes over ``length`` from t = 0: ``length / step`` with fixed steps; with cone
    steps Δt = clamp(t · cone_angle, step, max_step): fixed up to t0 = step / cone_angle,
    geometric (factor 1 + cone_angle a step) up to t1 = max_step / cone_angle, then max_step."""
    if cone_angle <= 0 or length <= step / cone_angle:
        return length / step + 1
    t0, t1 = step / cone_angle, max(step, max_step) / cone_angle
    geometric = math.log(min(length, t1) / t0) / math.log1p(cone_angle)
    return t0 / step + geometric + max(length - t1, 0.0) / max(step, max_step) + 1


def estimate(config, scene) -> MemoryEstimate:
    """The :class:`MemoryEstimate` of a resolved :class:`~ngp_warp.training.config.TrainConfig` on
    ``scene`` (a :class:`~ngp_warp.data.loading.Scene`): no allocation, plain arithmetic."""
    contraction = getattr(config, "contraction", None)
    contracted = contraction not in (None, "auto")
    levels = 1 if contracted else scene.occupancy_levels
    cells = levels * config.grid_resolution ** 3
    f = config.field
    table = f.n_levels * (1 << f.log2_hashmap_size) * f.n_features_per_level * 4 * TABLE_COPIES
    box = scene.occupancy_aabb.double()
    finest = float((box[3:] - box[:3]).norm())
    if contracted:  # steps over the contracted box [-2, 2]^3, twice its diagonal for the cone part
        per_ray = 2.0 * config.steps_per_diagonal + 1
    else:
        step = finest / config.steps_per_diagonal
        cone = config.cone_angle or 0.0
        per_ray = samples_per_ray(finest * 2 ** (levels - 1), step, cone, finest)
    samples = int(config.initial_rays * per_ray)
    widths = max(1.0, sample_width(f) / sample_width(FieldConfig()))  # FIELD_BYTES_PER_SAMPLE is at the defaults
    per_sample = MARCH_BYTES_PER_SAMPLE + FIELD_BYTES_PER_SAMPLE[bool(config.prune)] * widths
    mlps = mlp_parameters(f, len(scene.train.names)) * 4 * TABLE_COPIES
    return MemoryEstimate(cells, cells * GRID_BYTES_PER_CELL, table, mlps, samples, int(samples * per_sample))


def available_bytes(device: torch.device) -> int:
    """Memory free for a run on ``device``: CUDA's free memory, or the host's MemAvailable
    (Linux; the physical memory elsewhere)."""
    if device.type == "cuda":
        return int(torch.cuda.mem_get_info(device)[0])
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def _gb(n: float) -> str:
    return f"{n / 1e9:.1f} GB"


def check_fits(config, scene, device: torch.device, available: int | None = None) -> MemoryEstimate:
    """The estimate of ``config`` on ``scene``, or :class:`SettingsTooLarge` naming the part
    that does not fit in ``available`` bytes (default: :func:`available_bytes` of ``device``)
    or a first batch too large for one kernel call."""
    e = estimate(config, scene)
    levels = e.grid_cells // config.grid_resolution ** 3
    parts = (f"occupancy grid {levels} × {config.grid_resolution}³ cells: {_gb(e.grid_bytes)}, "
             f"hash tables {_gb(e.table_bytes)}, MLPs and codes {_gb(e.mlp_bytes)}, first batch {config.initial_rays} rays × up to "
             f"{e.first_batch_samples / max(config.initial_rays, 1):.3g} samples: {_gb(e.march_bytes)}")
    hint = ("lower grid_resolution, initial_rays, field.log2_hashmap_size, field.hidden, field.geo_features "
            "or the scene's aabb_scale, or step by cone_angle=0.004")
    if e.first_batch_samples > MAX_SAMPLES_PER_CALL:
        raise SettingsTooLarge(f"these settings march up to {e.first_batch_samples:.3g} samples in the first "
                               f"batch, more than one call takes ({MAX_SAMPLES_PER_CALL}) ({parts}); {hint}")
    free = available_bytes(device) if available is None else available
    if e.total > free:
        raise SettingsTooLarge(f"these settings need about {_gb(e.total)} but {device} has {_gb(free)} free "
                               f"({parts}); {hint}")
    return e
