"""FieldOptimizer's learning-rate schedule: a linear warm-up of ``warmup_steps``, then steps down
at 50, 75 and 90 % of the budget."""

import pytest
import torch

from ngp_warp.ops.field import FieldConfig, NGPField
from ngp_warp.training.config import TrainConfig
from ngp_warp.training.field_optimizer import FieldOptimizer


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
