"""End-to-end training on a tiny generated scene (CPU), checkpoints and resume."""

import pytest
import torch

from ngp_warp.checkpoint import CheckpointError, load_trainer, read_checkpoint, save_checkpoint
from ngp_warp.data import load_scene
from ngp_warp.evaluate import iter_test_renders
from ngp_warp.field import FieldConfig
from ngp_warp.metrics import psnr
from ngp_warp.scene import write_demo_scene
from ngp_warp.trainer import TrainConfig, Trainer


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    path = tmp_path_factory.mktemp("scene") / "demo"
    write_demo_scene(path, width=32, height=32, n_train=24, n_test=3, supersample=2)
    return path


def tiny_config(steps: int) -> TrainConfig:
    return TrainConfig(steps=steps, target_samples=1 << 13, grid_resolution=32, steps_per_diagonal=256,
                       field=FieldConfig(n_levels=8, log2_hashmap_size=14, finest_resolution=128.0, hidden=32))


def mean_psnr(trainer: Trainer) -> float:
    scores = [psnr(out["rgb"], gt) for _, out, gt in iter_test_renders(trainer)]
    return sum(scores) / len(scores)


def test_training_raises_held_out_psnr(tiny_scene):
    trainer = Trainer(load_scene(tiny_scene), tiny_config(300), device="cpu")
    before = mean_psnr(trainer)
    trainer.train(show_progress=False)
    after = mean_psnr(trainer)
    assert trainer.step_count == 300
    assert after > before + 8.0, (before, after)
    assert after > 20.0


def test_training_is_reproducible(tiny_scene):
    runs = []
    for _ in range(2):
        trainer = Trainer(load_scene(tiny_scene), tiny_config(15), device="cpu")
        trainer.train(show_progress=False)
        runs.append(trainer.field.encoding.params.detach().clone())
    torch.testing.assert_close(runs[0], runs[1], rtol=0, atol=1e-6)


def test_checkpoint_round_trip_and_resume(tiny_scene, tmp_path):
    trainer = Trainer(load_scene(tiny_scene), tiny_config(40), device="cpu")
    trainer.train(show_progress=False)
    ckpt = tmp_path / "checkpoint.pt"
    save_checkpoint(trainer, ckpt, tiny_scene, downscale=1)
    assert [p.name for p in tmp_path.iterdir()] == ["checkpoint.pt"]  # no temporary left behind

    loaded, record = load_trainer(ckpt, device="cpu")
    assert record["path"] == str(tiny_scene.resolve())
    split = trainer.scene.test
    a = trainer.render_image(split.c2w[0], split.intrinsics[0], split.width, split.height)
    b = loaded.render_image(split.c2w[0], split.intrinsics[0], split.width, split.height)
    torch.testing.assert_close(a["rgb"], b["rgb"], rtol=0, atol=0)
    torch.testing.assert_close(a["depth"], b["depth"], rtol=0, atol=0)

    loaded.config.steps = 5
    loaded.train(show_progress=False)
    assert loaded.step_count == 45


def test_checkpoint_errors_are_one_line(tmp_path):
    with pytest.raises(CheckpointError, match="no checkpoint there"):
        read_checkpoint(tmp_path / "missing.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        read_checkpoint(bad)
    torch.save({"something": 1}, tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match="not an ngp-warp checkpoint"):
        read_checkpoint(tmp_path / "other.pt")
