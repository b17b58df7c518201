"""benchmarks/near_support.py: a training image's PSNR by rows from the near and from a later start."""

import pytest

from ngp_warp.data.loading import load_scene
from ngp_warp.data.scene import write_demo_scene
from ngp_warp.training.config import TrainConfig, cpu_sizes
from ngp_warp.training.trainer import Trainer
from ngp_warp.outputs.evaluate import composite_on
from ngp_warp.outputs.metrics import psnr

from benchmark_scripts import load_benchmark

near_support = load_benchmark("near_support")


def test_bands_cover_the_image_and_a_start_past_the_scene_leaves_the_background(tmp_path):
    scene = load_scene(write_demo_scene(tmp_path / "demo", width=24, height=20, n_train=6, n_test=1, supersample=1))
    config = cpu_sizes(TrainConfig(steps=30))
    config.target_samples, config.grid_resolution = 1 << 10, 16
    config.field.log2_hashmap_size, config.field.n_levels, config.field.hidden = 12, 4, 16
    trainer = Trainer(scene, config, "cpu")
    trainer.train(show_progress=False)
    near = trainer.model.march.near
    same = near_support.band_psnrs(trainer, 2, near * 1.000001, 3)
    assert [(lo, hi) for lo, hi, _, _ in same] == [(0, 7), (7, 13), (13, 20)]
    assert all(abs(a - b) < 0.05 for _, _, a, b in same)  # the same start renders the same image
    assert trainer.model.march.near == near  # the trained near restored
    far = near_support.band_psnrs(trainer, 2, trainer.model.march.far * 0.999, 1)
    photo = composite_on(trainer.train_split.images[2], trainer.train_split.images.new_ones(3).float())
    assert far[0][3] == pytest.approx(psnr(photo.new_ones(photo.shape), photo), abs=0.05)  # white only
    assert far[0][2] > far[0][3] + 1.0  # the field explains the photo better than the white background
