"""``occupancy_open_steps``: for its first steps the trainer's grid refreshes count every visible
cell occupied (threshold 0); the first refresh after them culls as usual."""

import dataclasses

import pytest
import torch

from data_fixtures import nerf_synthetic
from ngp_warp.data.loading import load_scene
from ngp_warp.ops.field import FieldConfig
from ngp_warp.training.config import TrainConfig
from ngp_warp.training.trainer import Trainer


def _trainer(folder, open_steps: int, device: str = "cpu") -> Trainer:
    nerf_synthetic(folder, n_train=3, n_test=1, size=(16, 12))
    cfg = TrainConfig(steps=10_000, target_samples=2048, seed=3, occupancy_open_steps=open_steps, grid_resolution=16,
                      field=dataclasses.replace(FieldConfig(), n_levels=4, log2_hashmap_size=10, hidden=16))
    return Trainer(load_scene(folder), cfg, device=device)


def _refresh(trainer: Trainer, step: int, density) -> torch.Tensor:
    """The grid refreshed at ``step`` with ``density`` (world points → σ); the occupied cells."""
    assert trainer.phases.grid_update(step, density)
    return trainer.grid.occupied().reshape(-1).clone()


def _varied(points: torch.Tensor) -> torch.Tensor:
    """A density that differs across the box: far from constant, so a threshold culls some cells."""
    return torch.exp(4.0 * torch.sin(3.0 * points).sum(-1))


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
@pytest.mark.parametrize("open_steps", [0, 16, 32])  # 16: the refresh at step 16 is past the open steps
def test_the_grid_culls_no_visible_cell_while_open(tmp_path, open_steps, device):
    trainer = _trainer(tmp_path / "scene", open_steps, device)
    visible = (trainer.grid.occs >= 0).reshape(-1)
    occupied = _refresh(trainer, 16, _varied)
    if open_steps > 16:
        assert torch.equal(occupied, visible)  # every visible cell, whatever its density
        assert float(trainer.grid.threshold) == 0.0
    else:
        assert 0 < int(occupied.sum()) < int(visible.sum())  # the usual cull
    later = _refresh(trainer, 48, _varied)  # past the open steps: culled as a grid never opened
    assert 0 < int(later.sum()) < int(visible.sum())
    assert float(trainer.grid.threshold) > 0.0


def test_the_setting_is_checked():
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="occupancy_open_steps"):
            TrainConfig(occupancy_open_steps=bad).check()
    with pytest.raises(ValueError, match="grid_seen_only"):
        TrainConfig(grid_seen_only=1).check()
    TrainConfig(occupancy_open_steps=1000, grid_seen_only=True).check()
    TrainConfig(occupancy_open_steps=None, grid_seen_only=None, lr_warmup=None).check()  # None: per scene
