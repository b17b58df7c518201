"""Checkpoints: Trainer.state_dict round trips through the file, old checkpoints load, and a
damaged or foreign file is a one-line error."""

import dataclasses
from pathlib import Path

import pytest
import torch

from ngp_warp.training.checkpoint import FORMAT, CheckpointError, load_trainer, read_checkpoint, save_checkpoint
from ngp_warp.training.config import device_defaults, pixel_matched_resolution
from ngp_warp.data.loading import load_scene
from ngp_warp.training.trainer import Trainer
from test_train import tiny_config, tiny_scene  # noqa: F401  (tiny_scene: a fixture)


def assert_same_state(mine, theirs, where="state"):
    """Equal nested dicts / lists of tensors (bit for bit) and plain values."""
    if isinstance(mine, dict):
        assert mine.keys() == theirs.keys(), where
        for key in mine:
            assert_same_state(mine[key], theirs[key], f"{where}[{key!r}]")
    elif isinstance(mine, (list, tuple)):
        assert len(mine) == len(theirs), where
        for i, (a, b) in enumerate(zip(mine, theirs)):
            assert_same_state(a, b, f"{where}[{i}]")
    elif torch.is_tensor(mine):
        assert torch.equal(mine.cpu(), theirs.cpu()), where
    else:
        assert mine == theirs, where


def old_format_checkpoint(trainer: Trainer, scene_path: Path) -> dict:
    """A checkpoint as checkpoint.py wrote it before Trainer.state_dict: format v1, every
    part copied from the trainer's fields one by one."""
    averaged = trainer.averaged_weights()
    weights = trainer.weights
    return {
        "format": "ngp-warp-checkpoint-v1",
        "scene": {"path": str(Path(scene_path).resolve()), "downscale": 1},
        "train_config": dataclasses.asdict(trainer.config),
        "field": trainer.field.state_dict(),
        "grid": trainer.grid.state_dict(),
        "optimizer": weights.mlp_adam.state_dict(),
        "table_optimizer": None if weights.table_adam is None else weights.table_adam.state_dict(),
        "averaged": averaged,
        "step": trainer.step_count,
        "train_seconds": trainer.train_seconds,
        "n_rays": trainer.rays.n_rays,
        "sample_fraction": trainer.rays.fraction,
        "rng": torch.get_rng_state(),
    }


@pytest.mark.parametrize("lazy_table_adam", [False, True])
def test_old_format_checkpoint_loads_into_the_same_trainer_state(tiny_scene, tmp_path, lazy_table_adam):
    cfg = tiny_config(12)
    cfg.lazy_table_adam = lazy_table_adam
    trainer = Trainer(load_scene(tiny_scene), cfg, device="cpu")
    trainer.train(show_progress=False)
    trainer.step()  # leaves an update deferred: the checkpoint must hold it applied
    assert trainer.weights.pending
    old = old_format_checkpoint(trainer, tiny_scene)
    assert old["format"] == FORMAT and 0 < old["sample_fraction"] <= 1 and old["averaged"] is not None
    torch.save(old, tmp_path / "old.pt")
    loaded, record = load_trainer(tmp_path / "old.pt", device="cpu")
    assert record == old["scene"]
    mine, theirs = loaded.state_dict(), trainer.state_dict()
    # an old file has no curve; this run's is steps 1, 10 and 12
    assert mine.pop("curve").shape == (0, 6) and theirs.pop("curve").shape == (3, 6)
    assert_same_state(mine, theirs)
    assert loaded.config == trainer.config
    save_checkpoint(trainer, tmp_path / "new.pt", tiny_scene, 1)  # today's files have the same parts and the curve
    assert torch.load(tmp_path / "new.pt", weights_only=False).keys() == {*old.keys(), "curve"}
    split = trainer.scene.test
    a, b = (t.render_image(split.c2w[1], split.intrinsics[1], split.width, split.height) for t in (trainer, loaded))
    assert a["opacity"].std() > 0
    for key in ("rgb", "depth", "opacity"):
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=0)


def test_checkpoint_missing_a_part_is_a_one_line_error(tiny_scene, tmp_path):
    trainer = Trainer(load_scene(tiny_scene), tiny_config(1), device="cpu")
    save_checkpoint(trainer, tmp_path / "c.pt", tiny_scene, 1)
    state = torch.load(tmp_path / "c.pt", weights_only=False)
    del state["grid"]
    torch.save(state, tmp_path / "c.pt")
    with pytest.raises(CheckpointError, match="another ngp-warp version .no 'grid' in it"):
        load_trainer(tmp_path / "c.pt", device="cpu")


@pytest.mark.parametrize("lazy_table_adam", [False, True])
def test_checkpoint_round_trip_and_resume(tiny_scene, tmp_path, lazy_table_adam):
    cfg = tiny_config(40)
    cfg.lazy_table_adam = lazy_table_adam
    trainer = Trainer(load_scene(tiny_scene), cfg, device="cpu")
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
    for mine, theirs in zip(trainer.weights.optimizers(), loaded.weights.optimizers(), strict=True):
        for key, state in mine.state_dict()["state"].items():
            saved = theirs.state_dict()["state"][key]
            assert all(torch.equal(v, saved[k]) if torch.is_tensor(v) else v == saved[k] for k, v in state.items())

    assert loaded.curve == trainer.curve and [row[0] for row in trainer.curve] == [1, 10, 20, 30, 40]
    loaded.config.steps = 5
    loaded.train(show_progress=False)
    assert loaded.step_count == 45 and [row[0] for row in loaded.curve] == [1, 10, 20, 30, 40, 45]


def test_an_interrupted_run_keeps_its_pending_readout(tiny_scene, tmp_path, monkeypatch):
    trainer = Trainer(load_scene(tiny_scene), tiny_config(40), device="cpu")
    step = trainer.step

    def step_until_interrupted(progress):
        if trainer.step_count == 25:  # Ctrl-C: step 20's readout is on its way to the host
            raise KeyboardInterrupt
        return step(progress)

    monkeypatch.setattr(trainer, "step", step_until_interrupted)
    with pytest.raises(KeyboardInterrupt):
        trainer.train(show_progress=False)
    assert [row[0] for row in trainer.curve] == [1, 10, 20]  # what the interrupt's checkpoint saves


def test_checkpoint_written_behind_holds_the_weights_of_the_call(tiny_scene, tmp_path):
    from concurrent.futures import ThreadPoolExecutor

    trainer = Trainer(load_scene(tiny_scene), tiny_config(20), device="cpu")
    trainer.train(show_progress=False)
    save_checkpoint(trainer, tmp_path / "now.pt", tiny_scene, 1)
    claims = []
    with ThreadPoolExecutor(1) as writer:
        written = save_checkpoint(trainer, tmp_path / "behind.pt", tiny_scene, 1,
                                  before_write=lambda: claims.append(1), writer=writer)
        with torch.no_grad():  # what evaluation or more training would do to the live weights meanwhile
            for t in trainer.field.state_dict().values():
                if t.is_floating_point():
                    t.add_(1.0)
        written.result()
    assert claims == [1]
    now, behind = read_checkpoint(tmp_path / "now.pt"), read_checkpoint(tmp_path / "behind.pt")
    assert_same_state({k: v for k, v in now.items() if k != "rng"}, {k: v for k, v in behind.items() if k != "rng"})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["behind.pt", "now.pt"]  # no temporary left behind


@pytest.mark.cuda
def test_a_gpu_checkpoint_written_behind_waits_for_its_device_copy(tmp_path):
    # the copy to the host runs on the writer's own stream: it must wait for the device copy,
    # which here lands late (the GPU busy first), and not see the weights changed after the call
    from concurrent.futures import ThreadPoolExecutor

    from ngp_warp.data.scene import write_demo_scene

    scene = write_demo_scene(tmp_path / "scene", width=32, height=32, n_train=8, n_test=2, supersample=1,
                             device="cuda")  # rendered on the GPU: no CPU kernels needed
    trainer = Trainer(load_scene(scene), tiny_config(10), device="cuda")
    trainer.train(show_progress=False)
    save_checkpoint(trainer, tmp_path / "now.pt", scene, 1)

    def busy():  # about 0.1 s of GPU time queued after the weights' check, before the device copy
        torch.cuda._sleep(200_000_000)

    with ThreadPoolExecutor(1) as writer:
        written = save_checkpoint(trainer, tmp_path / "behind.pt", scene, 1, before_write=busy, writer=writer)
        with torch.no_grad():
            for t in trainer.field.state_dict().values():
                if t.is_floating_point():
                    t.add_(1.0)
        written.result()
    now, behind = read_checkpoint(tmp_path / "now.pt"), read_checkpoint(tmp_path / "behind.pt")
    assert_same_state({k: v for k, v in now.items() if k != "rng"}, {k: v for k, v in behind.items() if k != "rng"})


def test_checkpoint_without_a_weight_average_renders_its_weights(tiny_scene, tmp_path):
    trainer = Trainer(load_scene(tiny_scene), tiny_config(10), device="cpu")
    trainer.train(show_progress=False)
    ckpt = tmp_path / "checkpoint.pt"
    save_checkpoint(trainer, ckpt, tiny_scene, downscale=1)
    state = torch.load(ckpt, weights_only=False)
    assert state["averaged"] is not None
    del state["averaged"]  # as written before weight averaging existed
    torch.save(state, ckpt)
    loaded, _ = load_trainer(ckpt, device="cpu")
    for averaged, p in zip(loaded.weights.averaged, loaded.field.parameters()):
        assert torch.equal(averaged, p.detach())


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


def test_checkpoint_keeps_the_contributing_fraction_that_steers_the_ray_count(tiny_scene, tmp_path):
    trainer = Trainer(load_scene(tiny_scene), tiny_config(1), device="cpu")
    trainer.rays.fraction = 0.37  # as after steps where 37 % of the marched samples composite
    save_checkpoint(trainer, tmp_path / "c.pt", tiny_scene, 1)
    loaded, _ = load_trainer(tmp_path / "c.pt", device="cpu")
    assert loaded.rays.fraction == 0.37


def test_checkpoint_from_another_version_is_a_one_line_error(tiny_scene, tmp_path):
    trainer = Trainer(load_scene(tiny_scene), tiny_config(1), device="cpu")
    save_checkpoint(trainer, tmp_path / "c.pt", tiny_scene, 1)
    state = torch.load(tmp_path / "c.pt", weights_only=False)
    state["train_config"]["a_future_setting"] = 1
    torch.save(state, tmp_path / "c.pt")
    with pytest.raises(CheckpointError, match="another ngp-warp version.*a_future_setting"):
        load_trainer(tmp_path / "c.pt", device="cpu")


def test_checkpoint_with_a_setting_out_of_range_is_a_one_line_error(tiny_scene, tmp_path):
    trainer = Trainer(load_scene(tiny_scene), tiny_config(1), device="cpu")
    save_checkpoint(trainer, tmp_path / "c.pt", tiny_scene, 1)
    state = torch.load(tmp_path / "c.pt", weights_only=False)
    state["train_config"]["lr"] = -1.0
    torch.save(state, tmp_path / "c.pt")
    with pytest.raises(CheckpointError, match="lr must be a number > 0"):
        load_trainer(tmp_path / "c.pt", device="cpu")


def test_checkpoint_from_before_sub_rays_loads_as_one_ray_per_pixel(tiny_scene, tmp_path, monkeypatch):
    trainer = Trainer(load_scene(tiny_scene), tiny_config(1), device="cpu")
    save_checkpoint(trainer, tmp_path / "c.pt", tiny_scene, 1)
    state = torch.load(tmp_path / "c.pt", weights_only=False)
    del state["train_config"]["supersample"]
    torch.save(state, tmp_path / "c.pt")
    # resolve unset settings as CUDA would (2×2 sub-rays), on the CPU
    monkeypatch.setattr("ngp_warp.training.config.device_defaults", lambda cfg, _: device_defaults(cfg, "cuda"))
    assert Trainer(load_scene(tiny_scene), tiny_config(1), device="cpu").config.supersample == 2
    loaded, _ = load_trainer(tmp_path / "c.pt", device="cpu")
    assert loaded.config.supersample == 1


def test_checkpoint_from_before_distortion_spacing_keeps_world_distances(tiny_scene, tmp_path):
    trainer = Trainer(load_scene(tiny_scene), tiny_config(1), device="cpu")
    assert trainer.config.distortion_spacing == "normalised"
    save_checkpoint(trainer, tmp_path / "c.pt", tiny_scene, 1)
    assert load_trainer(tmp_path / "c.pt", device="cpu")[0].config.distortion_spacing == "normalised"
    state = torch.load(tmp_path / "c.pt", weights_only=False)
    del state["train_config"]["distortion_spacing"]
    torch.save(state, tmp_path / "c.pt")
    assert load_trainer(tmp_path / "c.pt", device="cpu")[0].config.distortion_spacing == "world"


def test_checkpoint_without_a_near_keeps_the_scenes_own(tmp_path):
    from ngp_warp.data.scene_unbounded import write_unbounded_scene

    folder = write_unbounded_scene(tmp_path / "u", width=8, height=8, n_train=12, n_test=2)
    scene = load_scene(folder)
    trainer = Trainer(scene, dataclasses.replace(tiny_config(1), contraction=None), device="cpu")
    assert trainer.config.near > 1.2 * scene.near  # a bounded capture's near from its cameras' focus
    save_checkpoint(trainer, tmp_path / "c.pt", folder, 1)
    assert load_trainer(tmp_path / "c.pt", device="cpu")[0].config.near == trainer.config.near
    state = torch.load(tmp_path / "c.pt", weights_only=False)
    del state["train_config"]["near"]  # written by a version that had no near setting
    torch.save(state, tmp_path / "c.pt")
    loaded = load_trainer(tmp_path / "c.pt", device="cpu")[0]
    assert loaded.config.near == scene.near == loaded.model.march.near


def test_contracted_checkpoint_from_before_the_environment_renders_over_black(tiny_scene, tmp_path):
    cfg = tiny_config(1)
    cfg.contraction = "l2"
    assert Trainer(load_scene(tiny_scene), cfg, device="cpu").field.environment is not None  # the default now
    cfg.field.environment = False  # as such a run was trained
    trainer = Trainer(load_scene(tiny_scene), cfg, device="cpu")
    save_checkpoint(trainer, tmp_path / "c.pt", tiny_scene, 1)
    state = torch.load(tmp_path / "c.pt", weights_only=False)
    del state["train_config"]["field"]["environment"]
    torch.save(state, tmp_path / "c.pt")
    loaded, _ = load_trainer(tmp_path / "c.pt", device="cpu")
    assert loaded.field.environment is None and loaded.config.field.environment is False


def test_trainer_resolves_an_unset_finest_resolution_and_checkpoints_it(tiny_scene, tmp_path):
    cfg = tiny_config(2)
    cfg.field.finest_resolution = None
    scene = load_scene(tiny_scene)
    trainer = Trainer(scene, cfg, device="cpu")
    assert cfg.field.finest_resolution is None  # the caller's config is left alone
    assert trainer.config.field.finest_resolution == pixel_matched_resolution(scene)
    save_checkpoint(trainer, tmp_path / "c.pt", tiny_scene, 1)
    loaded, _ = load_trainer(tmp_path / "c.pt", device="cpu")
    assert loaded.config.field.finest_resolution == trainer.config.field.finest_resolution


def test_trainer_checkpoints_the_resolved_device_defaults(tiny_scene, tmp_path):
    cfg = tiny_config(1)
    cfg.supersample = None
    trainer = Trainer(load_scene(tiny_scene), cfg, device="cpu")
    assert trainer.config.supersample == 1
    save_checkpoint(trainer, tmp_path / "c.pt", tiny_scene, 1)
    loaded, _ = load_trainer(tmp_path / "c.pt", device="cpu")
    assert loaded.config.supersample == 1


def test_checkpoint_keeps_the_field_box_and_an_old_one_the_files_box(tiny_scene, tmp_path):
    cfg = tiny_config(1)
    cfg.aabb_scale = 2
    trainer = Trainer(load_scene(tiny_scene), cfg, device="cpu")
    assert trainer.scene.occupancy_levels == 2
    save_checkpoint(trainer, tmp_path / "c.pt", tiny_scene, 1)
    loaded = load_trainer(tmp_path / "c.pt", device="cpu")[0]
    assert loaded.config.aabb_scale == 2 and torch.equal(loaded.scene.aabb, trainer.scene.aabb)
    trainer = Trainer(load_scene(tiny_scene), tiny_config(1), device="cpu")
    assert trainer.config.aabb_scale is None  # "auto" keeps a NeRF-synthetic scene's box
    save_checkpoint(trainer, tmp_path / "c.pt", tiny_scene, 1)
    state = torch.load(tmp_path / "c.pt", weights_only=False)
    del state["train_config"]["aabb_scale"]
    torch.save(state, tmp_path / "c.pt")
    loaded = load_trainer(tmp_path / "c.pt", device="cpu")[0]
    assert loaded.config.aabb_scale is None and torch.equal(loaded.scene.aabb, trainer.scene.aabb)


def test_a_contracted_checkpoint_rebuilds_its_inner_box_or_says_it_cannot(tiny_scene, tmp_path):
    cfg = tiny_config(1)
    cfg.contraction, cfg.contraction_fit = "l2", "seen"
    trainer = Trainer(load_scene(tiny_scene), cfg, device="cpu")
    save_checkpoint(trainer, tmp_path / "c.pt", tiny_scene, 1)
    loaded = load_trainer(tmp_path / "c.pt", device="cpu")[0]
    assert loaded.config.contraction_fit == "seen"
    assert loaded.grid.inner_aabb_host == trainer.grid.inner_aabb_host
    assert loaded.model.march.step_size == trainer.model.march.step_size
    state = torch.load(tmp_path / "c.pt", weights_only=False)
    state["grid"]["inner_aabb"] = state["grid"]["inner_aabb"] * 2  # as if the scene had moved since
    torch.save(state, tmp_path / "c.pt")
    with pytest.raises(CheckpointError, match="another contraction box than the run trained in") as err:
        load_trainer(tmp_path / "c.pt", device="cpu")
    assert "\n" not in str(err.value)


def test_near_setting_starts_the_march_and_the_distortion_spacing_there_and_is_checkpointed(tiny_scene, tmp_path):
    scene = load_scene(tiny_scene)
    assert Trainer(scene, tiny_config(1), device="cpu").config.near == scene.near  # unset: the scene's
    cfg = tiny_config(1)
    cfg.near, cfg.distortion_weight = 2.5, 0.5
    trainer = Trainer(scene, cfg, device="cpu")
    assert trainer.model.march.near == trainer.scene.near == 2.5 != scene.near
    seen = []

    def recording(phase, fn):  # the distortion loss's normalised distance s = 1 − near/t takes this near
        def call(*args, **kwargs):
            if phase == "distortion":
                seen.append(args[-1])
            return fn(*args, **kwargs)
        return call

    trainer.instrument(recording)
    trainer.step()
    assert seen == [2.5]
    save_checkpoint(trainer, tmp_path / "c.pt", tiny_scene, 1)
    loaded = load_trainer(tmp_path / "c.pt", device="cpu")[0]
    assert loaded.config.near == 2.5 and loaded.model.march.near == 2.5
