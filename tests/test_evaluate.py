"""The evaluation's image conversions (depth maps as uint8), and its scores of views rendered together."""

from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from ngp_warp.data.loading import load_scene
from ngp_warp.data.scene import write_demo_scene
from ngp_warp.ops.field import FieldConfig
from ngp_warp.outputs.evaluate import EVAL_VIEWS_TOGETHER, depth_to_uint8, evaluate, iter_test_renders, to_uint8
from ngp_warp.outputs.metrics import psnr, ssim
from ngp_warp.training.config import TrainConfig
from ngp_warp.training.trainer import Trainer


def test_depth_spans_the_opaque_pixels_near_bright():
    gen = torch.Generator().manual_seed(0)
    depth = 0.5 + 4 * torch.rand(24, 32, generator=gen)
    opacity = torch.rand(24, 32, generator=gen)
    img = depth_to_uint8(depth * opacity, opacity)  # the renderer's depth is weighted by opacity
    opaque = (opacity > 0.5).numpy()
    d = depth.numpy()
    want = 1.0 - (d - d[opaque].min()) / (d[opaque].max() - d[opaque].min())
    want = np.where(opaque, np.floor(want * 255 + 0.5), 0)
    assert img.dtype == np.uint8 and img.shape == (24, 32)
    assert np.abs(img.astype(int) - want).max() <= 1  # float32 rounding at .5
    assert img[opaque].max() == 255 and img[opaque].min() == 0 and (img[~opaque] == 0).all()


def test_depth_of_a_transparent_view_is_black():
    depth = torch.rand(8, 8) * 3
    assert (depth_to_uint8(depth, torch.full((8, 8), 0.2)) == 0).all()


def test_depth_maps_together_each_keep_their_own_range():
    gen = torch.Generator().manual_seed(1)
    depth, opacity = 0.5 + 4 * torch.rand(3, 12, 16, generator=gen), torch.rand(3, 12, 16, generator=gen)
    depth[1] *= 3  # another range
    opacity[2] = 0.1  # transparent
    together = depth_to_uint8(depth * opacity, opacity)
    assert together.shape == (3, 12, 16)
    for k in range(3):
        assert np.array_equal(together[k], depth_to_uint8(depth[k] * opacity[k], opacity[k]))


def test_views_scored_together_score_as_each_alone(tmp_path):
    n_test = EVAL_VIEWS_TOGETHER + 2  # a full group and a short one
    scene = write_demo_scene(tmp_path / "demo", width=16, height=16, n_train=8, n_test=n_test, supersample=1)
    config = TrainConfig(steps=30, target_samples=1 << 11, grid_resolution=16, steps_per_diagonal=128,
                         field=FieldConfig(n_levels=4, log2_hashmap_size=12, finest_resolution=64.0, hidden=16))
    trainer = Trainer(load_scene(scene), config, device="cpu")
    trainer.train(show_progress=False)
    (tmp_path / "run").mkdir()
    metrics = evaluate(trainer, tmp_path / "run", show_progress=False)
    alone = list(iter_test_renders(trainer))
    assert [m["image"] for m in metrics["per_image"]] == [name for name, _, _ in alone]
    for record, (name, out, gt) in zip(metrics["per_image"], alone, strict=True):
        assert record["psnr"] == pytest.approx(psnr(out["rgb"], gt), abs=1e-4)
        assert record["ssim"] == pytest.approx(ssim(out["rgb"], gt), abs=1e-5)
        written = iio.imread(tmp_path / "run" / "renders" / f"{Path(name).stem}.png")
        assert np.abs(written.astype(int) - to_uint8(out["rgb"]).astype(int)).max() <= 1
    assert len({round(m["psnr"], 3) for m in metrics["per_image"]}) > 1  # the views differ
