"""FieldOptimizer's learning-rate schedule: a linear warm-up over the first 100 steps, then
steps down to a third at 50, 75 and 90 % of the budget."""

import pytest
import torch

from ngp_warp.ops.field import FieldConfig, NGPField
from ngp_warp.training.field_optimizer import FieldOptimizer


def _optimizer() -> FieldOptimizer:
    field = NGPField(torch.tensor([-1.0, -1, -1, 1, 1, 1]), FieldConfig(n_levels=2, log2_hashmap_size=8))
    return FieldOptimizer(field, 1e-2, 0.0, 0.0, True)


def test_warm_up_is_linear_over_the_first_100_steps():
    opt = _optimizer()
    assert opt.learning_rate(0, 0.0) == pytest.approx(1e-4)
    assert opt.learning_rate(50, 0.0) == pytest.approx(0.51e-2)
    assert opt.learning_rate(99, 0.0) == pytest.approx(1e-2)  # 0.01 + 0.99
    assert opt.learning_rate(100, 0.0) == opt.learning_rate(10_000, 0.0) == pytest.approx(1e-2)


def test_steps_down_with_progress():
    opt = _optimizer()
    rates = [opt.learning_rate(10_000, p) for p in (0.49, 0.5, 0.75, 0.9)]
    assert rates == pytest.approx([1e-2, 3.3e-3, 1.089e-3, 3.5937e-4])
