"""FieldOptimizer's learning-rate schedule: a linear warm-up of ``warmup_steps``, then steps down
at 50, 75 and 90 % of the budget."""

import dataclasses

import pytest
import torch

from data_fixtures import nerf_synthetic
from ngp_warp.data.loading import load_scene

from ngp_warp.ops.field import FieldConfig, NGPField
from ngp_warp.training.config import TrainConfig
from ngp_warp.training.field_optimizer import FieldOptimizer
from ngp_warp.training.trainer import Trainer


def _optimizer(warmup_steps: int) -> FieldOptimizer:
    field = NGPField(torch.tensor([-1.0, -1, -1, 1, 1, 1]), FieldConfig(n_levels=2, log2_hashmap_size=8))
    return FieldOptimizer(field, 1e-2, 0.0, 0.0, True, warmup_steps)


@pytest.mark.parametrize("warmup", [1, 100, 1000])
def test_warm_up_is_linear_over_its_steps(warmup):
    opt = _optimizer(warmup)
    assert opt.learning_rate(0, 0.0) == pytest.approx(1e-4)
    assert opt.learning_rate(warmup // 2, 0.0) == pytest.approx(1e-2 * min(1.0, 0.01 + (warmup // 2) / warmup))
    assert opt.learning_rate(warmup, 0.0) == opt.learning_rate(10 * warmup, 0.0) == pytest.approx(1e-2)


def test_steps_down_with_progress():
    opt = _optimizer(100)
    rates = [opt.learning_rate(10_000, p) for p in (0.49, 0.5, 0.75, 0.9)]
    assert rates == pytest.approx([1e-2, 3.3e-3, 1.089e-3, 3.5937e-4])


def test_the_setting_is_checked():
    with pytest.raises(ValueError, match="lr_warmup"):
        TrainConfig(lr_warmup=0).check()
    TrainConfig(lr_warmup=1000).check()


@pytest.mark.parametrize("warmup", [100, 1000])
def test_the_trainer_steps_at_the_warm_up_it_is_given(tmp_path, warmup):
    nerf_synthetic(tmp_path / "scene", n_train=3, n_test=1, size=(16, 12))
    cfg = TrainConfig(steps=10_000, target_samples=2048, seed=3, lr_warmup=warmup, weight_average=0.0,
                      field=dataclasses.replace(FieldConfig(), n_levels=4, log2_hashmap_size=10, hidden=16))
    trainer = Trainer(load_scene(tmp_path / "scene"), cfg, device="cpu")
    trainer.train(show_progress=False, stop=(5, None))  # five steps of a long budget: no step-down yet
    applied = [group["lr"] for opt in trainer.weights.optimizers() for group in opt.param_groups]
    last = trainer.step_count - 1  # the last update's step
    assert applied == pytest.approx([1e-2 * (0.01 + last / warmup)] * len(applied))
