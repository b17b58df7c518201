"""Issue 22: run folders, signals, periodic and non-finite checkpoints, the memory estimate,
strict metrics JSON, umask-honouring atomic outputs and the data checks."""

import json
import logging
import math
import os
import signal
import stat
import threading

import numpy as np
import pytest
import torch

from ngp_warp.atomic import atomic_dir, atomic_write_text, remove_stale_partials
from ngp_warp.training.checkpoint import CheckpointError, NonFiniteWeights, load_trainer, save_checkpoint
from ngp_warp.training.config import TrainConfig, apply_overrides
from ngp_warp.data.loading import load_scene
from ngp_warp.outputs.evaluate import finite_or_null
from ngp_warp.training.memory_estimate import SettingsTooLarge, check_fits, samples_per_ray
from ngp_warp.training.run_folder import RunFolder, RunFolderError, Terminated, sigterm_as_interrupt
from ngp_warp.training.trainer import Trainer, TrainingDiverged
from data_fixtures import instant_ngp
from test_train import tiny_config, tiny_scene  # noqa: F401  (tiny_scene: a fixture)


@pytest.mark.parametrize("umask", [0o022, 0o077, 0o002])
def test_atomic_outputs_follow_the_umask(tmp_path, umask):
    previous = os.umask(umask)
    try:
        atomic_write_text(tmp_path / "m.json", "{}")
        with atomic_dir(tmp_path / "renders") as d:
            (d / "a.png").write_bytes(b"x")
    finally:
        os.umask(previous)
    assert stat.S_IMODE((tmp_path / "m.json").stat().st_mode) == 0o666 & ~umask
    assert stat.S_IMODE((tmp_path / "renders").stat().st_mode) == 0o777 & ~umask


def test_stale_partials_are_removed_and_nothing_else(tmp_path):
    (tmp_path / ".renders.ab_cd123.partial").mkdir()
    (tmp_path / ".metrics.json.x1y2z3w4.partial").write_text("half")
    (tmp_path / ".orbit.mp4.abcdefgh.partial.mp4").write_text("half")
    keep = [".hidden", "notes.partial", "renders", ".ngp.partial"]
    for name in keep:
        (tmp_path / name).write_text("mine")
    removed = remove_stale_partials(tmp_path)
    assert len(removed) == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(keep)


def test_atomic_dir_refuses_to_replace_a_file(tmp_path):
    (tmp_path / "renders").write_text("a file")
    with pytest.raises(NotADirectoryError):
        with atomic_dir(tmp_path / "renders"):
            pass
    assert (tmp_path / "renders").read_text() == "a file"


def test_run_folder_refuses_another_run_and_overwrites_only_at_the_first_write(tmp_path, caplog):
    out = tmp_path / "run"
    out.mkdir()
    (out / "checkpoint.pt").write_text("old")
    (out / "transforms_refined.json").write_text("old")
    (out / "renders").mkdir()
    (out / "notes.txt").write_text("the user's")
    with pytest.raises(RunFolderError, match="holds another run .*--resume.*--overwrite"):
        RunFolder(out)
    with pytest.raises(RunFolderError, match="replace it with --overwrite, or choose"):
        RunFolder(out, flags=(None, "--overwrite"))
    folder = RunFolder(out, overwrite=True)
    assert (out / "checkpoint.pt").exists()  # nothing goes before the run writes
    folder.claim()
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    assert caplog.messages == [f"ngp-warp: {out}: replaced the previous run's outputs; other files there are kept, "
                               f"perhaps made from it: notes.txt"]
    RunFolder(out)  # empty of runs again
    (out / "checkpoint.pt").write_text("mine")
    RunFolder(out, resume=True).claim()
    assert (out / "checkpoint.pt").read_text() == "mine"  # resuming keeps the run
    assert len(caplog.messages) == 1  # a resumed run's own files are no news


def test_run_folder_refuses_outputs_of_the_wrong_kind(tmp_path):
    (tmp_path / "renders").write_text("not a folder")
    with pytest.raises(RunFolderError, match="renders is a file"):
        RunFolder(tmp_path, overwrite=True)
    with pytest.raises(RunFolderError, match="is a file, not an output folder"):
        RunFolder(tmp_path / "renders")


def test_sigterm_raises_terminated_in_the_main_thread_and_the_handler_comes_back():
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Terminated):
        with sigterm_as_interrupt():
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(1000):  # the handler runs between bytecodes
                sum(range(100))
    assert signal.getsignal(signal.SIGTERM) is before
    assert issubclass(Terminated, KeyboardInterrupt)


def test_periodic_checkpoints_come_at_readouts(tiny_scene):
    trainer = Trainer(load_scene(tiny_scene), tiny_config(25), device="cpu")
    saved = []
    trainer.train(show_progress=False, checkpoint=lambda: saved.append(trainer.step_count), checkpoint_every=0.0)
    assert saved == [1, 10, 20]
    never = []
    trainer.config.steps = 12
    trainer.train(show_progress=False, checkpoint=lambda: never.append(1), checkpoint_every=3600.0)
    assert never == []


def test_divergence_stops_training_and_nan_weights_are_never_saved(tiny_scene, tmp_path):
    config = apply_overrides(tiny_config(40), ["lr=1e30"])
    trainer = Trainer(load_scene(tiny_scene), config, device="cpu")
    with pytest.raises(TrainingDiverged, match="loss is nan at step"):
        trainer.train(show_progress=False)
    assert trainer.step_count < 40
    calls = []
    with pytest.raises(NonFiniteWeights, match="not finite"):
        save_checkpoint(trainer, tmp_path / "c.pt", tiny_scene, 1, before_write=lambda: calls.append(1))
    assert calls == [] and not list(tmp_path.iterdir())


def test_a_diverged_field_is_never_checkpointed_by_the_periodic_save(tiny_scene, tmp_path):
    # the loss is read a readout late, except before a checkpoint: the save never meets NaN weights
    trainer = Trainer(load_scene(tiny_scene), apply_overrides(tiny_config(40), ["lr=1e30"]), device="cpu")
    saved = []

    def save():
        save_checkpoint(trainer, tmp_path / "c.pt", tiny_scene, 1)
        saved.append(trainer.step_count)

    with pytest.raises(TrainingDiverged, match=r"loss is nan at step \d+ \(try a lower lr\)"):
        trainer.train(show_progress=False, checkpoint=save, checkpoint_every=0.0)
    assert saved and saved == sorted(saved) and trainer.step_count <= max(saved) + 10


def test_checkpoint_of_another_scene_or_other_shapes_is_one_line(tiny_scene, tmp_path):
    trainer = Trainer(load_scene(tiny_scene), tiny_config(1), device="cpu")
    save_checkpoint(trainer, tmp_path / "c.pt", tiny_scene, 1)
    other = tmp_path / "other"
    instant_ngp(other, n=9, size=(16, 12))
    with pytest.raises(CheckpointError, match="is not the scene .* was trained on"):
        load_trainer(tmp_path / "c.pt", device="cpu", scene_path=other)
    state = torch.load(tmp_path / "c.pt", weights_only=False)
    state["train_config"]["field"]["hidden"] = 16
    torch.save(state, tmp_path / "c.pt")
    with pytest.raises(CheckpointError, match="do not fit its settings") as e:
        load_trainer(tmp_path / "c.pt", device="cpu")
    assert "\n" not in str(e.value)


def test_memory_estimate_refuses_what_cannot_fit(tiny_scene):
    scene = load_scene(tiny_scene)
    config = apply_overrides(tiny_config(1), ["grid_resolution=100000"])
    with pytest.raises(SettingsTooLarge, match="need about .* 100000³ cells"):
        check_fits(config, scene, torch.device("cpu"))
    with pytest.raises(SettingsTooLarge):
        Trainer(scene, config, device="cpu")  # before allocating the grid
    small = check_fits(tiny_config(1), scene, torch.device("cpu"))
    assert small.total < 1e9
    with pytest.raises(SettingsTooLarge, match="has 0.0 GB free"):
        check_fits(tiny_config(1), scene, torch.device("cpu"), available=1000)


@pytest.mark.parametrize("cone, max_step", [(0.0, 1.0), (1 / 256, 1.0), (1 / 256, 0.05), (0.02, 10.0)])
def test_samples_per_ray_counts_the_cone_steps(cone, max_step):
    step, length, t, n = 1e-3, 40.0, 0.0, 0
    while t < length:
        t += min(max(t * cone, step), max_step) if cone > 0 else step
        n += 1
    assert samples_per_ray(length, step, cone, max_step) == pytest.approx(n, rel=0.02, abs=2)


def test_settings_that_are_not_finite_are_refused():
    for setting in ("lr=inf", "seconds=inf", "cone_angle=nan", "field.finest_resolution=inf"):
        with pytest.raises(ValueError, match="finite|number"):
            apply_overrides(TrainConfig(), [setting]).check()
    with pytest.raises(ValueError, match="seed"):
        TrainConfig(seed=10**30).check()


def test_metrics_json_is_strict_with_a_note():
    metrics = finite_or_null({"psnr": math.nan, "ssim": 0.5, "per_image": [{"psnr": math.inf}]})
    text = json.dumps(metrics, allow_nan=False)
    assert json.loads(text)["psnr"] is None and "psnr (nan)" in metrics["notes"][0]


def test_rescaled_w_h_warns_once_and_scales_the_intrinsics(tmp_path, caplog):
    meta, _ = instant_ngp(tmp_path / "s", n=7, size=(8, 6))
    meta.update(w=16, h=12, fl_x=10.0, fl_y=10.0, cx=8.0, cy=6.0)
    (tmp_path / "s" / "transforms.json").write_text(json.dumps(meta))
    with caplog.at_level(logging.WARNING, logger="ngp_warp.data.loading"):
        scene = load_scene(tmp_path / "s")
    warnings = [r for r in caplog.records if "w x h = 16x12 but the image is 8x6" in r.message]
    assert len(warnings) == 2  # one per split
    assert torch.allclose(scene.train.intrinsics[0], torch.tensor([5.0, 5.0, 4.0, 3.0]))


def test_a_sigterm_during_cli_training_saves_and_exits_143(tiny_scene, tmp_path, capsys):
    from ngp_warp.cli import main

    out = tmp_path / "run"
    timer = threading.Timer(15.0, os.kill, (os.getpid(), signal.SIGTERM))
    timer.start()
    try:
        code = main(["train", str(tiny_scene), "--out", str(out), "--steps", "100000", "--no-video",
                     "--device", "cpu", "--quiet", "--target-samples", "2048", "--set", "grid_resolution=32",
                     "--set", "field.log2_hashmap_size=14"])
    finally:
        timer.cancel()
    err = capsys.readouterr().err
    assert code == 143, err
    assert "terminated (SIGTERM) at step" in err and "Traceback" not in err
    state = torch.load(out / "checkpoint.pt", weights_only=False)
    assert state["step"] > 0 and np.isfinite(state["train_seconds"])
    assert sorted(p.name for p in out.iterdir()) == ["checkpoint.pt", "normalisation.json", "training_curve.csv"]
    steps = [int(line.split(",")[0]) for line in (out / "training_curve.csv").read_text().splitlines()[1:]]
    assert steps == state["curve"][:, 0].int().tolist() and 0 < len(steps) and steps[-1] <= state["step"]
