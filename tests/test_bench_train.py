"""benchmarks/bench_train.py: every test view's score at each checkpoint, and the worst named."""

import dataclasses
import functools

import numpy as np
import pytest

from benchmark_scripts import load_benchmark
from data_fixtures import nerf_synthetic
from ngp_warp.data.loading import load_scene
from ngp_warp.outputs import evaluate
from ngp_warp.ops.field import FieldConfig
from ngp_warp.training.config import TrainConfig
from ngp_warp.training.trainer import Trainer

bench_train = load_benchmark("bench_train")


@pytest.mark.parametrize("codes", [0, 4])
def test_rows_hold_every_views_score(tmp_path, capsys, monkeypatch, codes):
    # a short fit: what is tested is which scores the rows hold, not the fit
    monkeypatch.setattr(evaluate, "fit_appearance_code", functools.partial(evaluate.fit_appearance_code, iterations=5))
    nerf_synthetic(tmp_path / "scene", n_train=4, n_test=3, size=(24, 16))
    scene = load_scene(tmp_path / "scene")
    cfg = TrainConfig(seconds=0.6, target_samples=2048, seed=1, supersample=1,
                      field=dataclasses.replace(FieldConfig(), appearance_dim=codes, n_levels=4, log2_hashmap_size=10))
    trainer = Trainer(scene, cfg, device="cpu")
    rows = bench_train.train_and_evaluate(trainer, [0.3, 0.6], test_every=1)
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(rows) == len(lines) == 2
    for row, line in zip(rows, lines):
        assert list(row["per_view"]) == scene.test.names
        assert row["psnr"] == pytest.approx(np.mean(list(row["per_view"].values())))
        shown = row["per_view_fitted_right_half"] if codes else row["per_view"]
        assert ("per_view_fitted_right_half" in row) == bool(codes)
        worst = min(shown, key=shown.get)
        assert line.endswith(f"worst view {worst.split('/')[-1]} {shown[worst]:.2f}")
        if codes:
            assert row["psnr_fitted_right_half"] == pytest.approx(np.mean(list(shown.values())))
    assert len(set(rows[-1]["per_view"].values())) == len(scene.test.names)  # scores of different views
