"""Smoke tests of the ngp-warp command, including its one-line errors on bad input."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import imageio.v3 as iio
import pytest
import torch

from ngp_warp import _wp
from ngp_warp.cli import main
from ngp_warp.data.loading import load_scene
from ngp_warp.data.scene import write_demo_scene
from ngp_warp.training.checkpoint import read_checkpoint

FAST = ["--device", "cpu", "--quiet", "--target-samples", "4096"]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli") / "scene"
    write_demo_scene(path, width=24, height=24, n_train=12, n_test=2, supersample=1)
    return path


def one_line_error(capsys, prefix="ngp-warp: error: "):
    err = capsys.readouterr().err.strip().splitlines()
    assert err and err[-1].startswith(prefix), err
    assert not any("Traceback" in line for line in err)
    return err[-1]


def test_train_eval_render(scene, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["train", str(scene), "--out", str(out), "--steps", "20", "--frames", "3",
                 "--set", "distortion_weight=0.01", *FAST]) == 0
    err = capsys.readouterr().err
    assert "distortion loss weight 0.01 (normalised), 1x1 rays per pixel, starting 0.3 from their camera" in err
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ("psnr", "ssim", "train_seconds", "steps", "per_image"):
        assert key in metrics
    wall = metrics["wall_seconds"]
    assert list(wall) == ["start_up", "training", "checkpoint", "evaluation", "video"]
    assert all(s > 0 for s in wall.values()) and wall["training"] >= metrics["train_seconds"]
    assert f"wall clock {sum(wall.values()):.1f} s: start-up {wall['start_up']:.1f} s, training" in err
    assert metrics["steps"] == 20 and len(metrics["per_image"]) == 2
    assert sorted(p.name for p in (out / "renders").iterdir()) == ["r_0.png", "r_1.png"]
    assert len(list((out / "depth").iterdir())) == 2
    assert any(p.name.startswith("orbit.") for p in out.iterdir())
    assert not [p for p in out.rglob("*") if "partial" in p.name]

    assert main(["eval", str(out), "--device", "cpu", "--quiet"]) == 0
    assert "PSNR" in capsys.readouterr().out
    assert main(["render", str(out), "--video", "spin.gif", "--frames", "2", "--device", "cpu", "--quiet"]) == 0
    assert (out / "spin.gif").stat().st_size > 0
    for near, blank in ((0.5, False), (100.0, True)):  # the cameras are about 4 from a subject within ±1.5
        assert main(["render", str(out), "--video", "near.gif", "--frames", "2", "--near", str(near), "--device", "cpu",
                     "--quiet"]) == 0
        frames = iio.imread(out / "near.gif", index=None)[..., :3]
        assert bool((frames == 255).all()) == blank, near  # beyond the subject: only the white background
    assert main(["render", str(out), "--video", "far.gif", "--near", "1e5", "--device", "cpu"]) == 2
    assert "--near must be below the rays' far distance" in capsys.readouterr().err

    assert main(["train", str(scene), "--out", str(out), "--resume", "--steps", "5", "--no-video", *FAST]) == 0
    assert json.loads((out / "metrics.json").read_text())["steps"] == 25


def test_demo_runs_end_to_end(tmp_path):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--steps", "10", "--no-video", *FAST]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["test_split"] == "test" and metrics["n_test_images"] > 0
    assert (out / "scene" / "transforms_train.json").exists()


def test_missing_scene_is_one_line(tmp_path, capsys):
    assert main(["train", str(tmp_path / "nope"), "--out", str(tmp_path / "o"), "--steps", "1", *FAST]) == 2
    assert "nope" in one_line_error(capsys)
    assert not (tmp_path / "o").exists()  # nothing left behind


def test_malformed_transforms_is_one_line(tmp_path, capsys):
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "transforms_train.json").write_text("{not json")
    assert main(["train", str(tmp_path / "bad"), "--out", str(tmp_path / "o"), "--steps", "1", *FAST]) == 2
    assert "transforms_train.json" in one_line_error(capsys)


def test_unwritable_output_is_one_line(scene, tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main(["train", str(scene), "--out", str(blocker / "sub"), "--steps", "1", *FAST]) == 2
    assert "not writable" in one_line_error(capsys)


def test_eval_without_checkpoint_is_one_line(tmp_path, capsys):
    assert main(["eval", str(tmp_path), "--device", "cpu"]) == 2
    assert "no checkpoint" in one_line_error(capsys)


def test_cuda_request_without_gpu_is_one_line(scene, tmp_path, capsys):
    if _wp.cuda_available():
        pytest.skip("this machine has a GPU")
    assert main(["train", str(scene), "--out", str(tmp_path / "o"), "--device", "cuda", "--quiet"]) == 2
    assert "no CUDA GPU" in one_line_error(capsys)


def test_resume_keeps_the_recorded_downscale(scene, tmp_path):
    from ngp_warp.training.checkpoint import read_checkpoint

    out = tmp_path / "run"
    common = ["--no-video", *FAST]
    assert main(["train", str(scene), "--out", str(out), "--steps", "3", "--downscale", "2", *common]) == 0
    assert main(["train", str(scene), "--out", str(out), "--resume", "--steps", "2", *common]) == 0
    state = read_checkpoint(out / "checkpoint.pt")
    assert state["scene"]["downscale"] == 2 and state["step"] == 5
    assert state["scene"]["path"] == str(scene.resolve())
    # the curve continues across the resume: readouts at step 1 and at each run's last step
    lines = (out / "training_curve.csv").read_text().splitlines()
    assert lines[0] == "step,seconds,loss,psnr,rays,samples"
    rows = [[float(x) for x in line.split(",")] for line in lines[1:]]
    assert [int(r[0]) for r in rows] == [1, 3, 5]
    assert all(a[1] <= b[1] for a, b in zip(rows, rows[1:]))
    assert rows[-1][1] == pytest.approx(state["train_seconds"], abs=0.5)
    assert all(r[2] > 0 and 0 < r[3] < 100 and r[4] > 0 and r[5] > 0 for r in rows)
    torch.testing.assert_close(torch.tensor([r[:4] for r in rows], dtype=torch.float64), state["curve"][:, :4],
                               rtol=1e-4, atol=2e-3)


def test_resume_refuses_other_settings_and_eval_keeps_the_training_record(scene, tmp_path, capsys):
    out = tmp_path / "run"
    common = ["--no-video", *FAST]
    assert main(["train", str(scene), "--out", str(out), "--steps", "2", "--seed", "3", *common]) == 0
    assert f"{out / 'normalisation.json'}" in capsys.readouterr().out
    record = json.loads((out / "normalisation.json").read_text())
    assert len(record["world_from_scene"]) == 4 and record["scale"] > 0
    for argv, message in ((["--seed", "4"], "--seed 4 with --resume: "), (["--seed", "0"], "--seed 0 with --resume: "),
                          (["--target-samples", "2048"], "--target-samples 2048 with --resume: ")):
        assert main(["train", str(scene), "--out", str(out), "--resume", "--steps", "1", *common, *argv]) == 2
        err = one_line_error(capsys)
        assert message in err and err.rstrip().endswith("(a resumed run keeps it)")
    assert main(["train", str(scene), "--out", str(out), "--resume", "--steps", "1", "--seed", "3", *common]) == 0
    capsys.readouterr()
    wall = json.loads((out / "metrics.json").read_text())["wall_seconds"]
    assert main(["eval", str(out), "--device", "cpu", "--quiet"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["wall_seconds"] == wall and metrics["steps"] == 3
    printed = capsys.readouterr().out
    assert "metrics.json" in printed and "checkpoint.pt" not in printed  # eval writes no checkpoint


def test_ctrl_c_in_the_evaluation_keeps_the_checkpoint_and_names_eval(scene, tmp_path, capsys, monkeypatch):
    from ngp_warp.outputs import evaluate

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(evaluate, "evaluate", interrupted)
    out = tmp_path / "run"
    assert main(["train", str(scene), "--out", str(out), "--steps", "2", "--no-video", *FAST]) == 130
    assert f"the trained checkpoint is kept (evaluate it with ngp-warp eval {out})" in capsys.readouterr().err
    assert read_checkpoint(out / "checkpoint.pt")["step"] == 2


def test_ctrl_c_in_the_evaluation_says_when_the_checkpoint_failed(scene, tmp_path, capsys, monkeypatch):
    from ngp_warp.outputs import evaluate
    from ngp_warp.training import checkpoint

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    def disk_full(state, path):
        raise OSError("No space left on device")

    monkeypatch.setattr(evaluate, "evaluate", interrupted)
    monkeypatch.setattr(checkpoint, "_write", disk_full)
    out = tmp_path / "run"
    assert main(["train", str(scene), "--out", str(out), "--steps", "2", "--no-video", *FAST]) == 130
    err = capsys.readouterr().err
    assert "the checkpoint was not written (No space left on device)" in err and "is kept" not in err


def test_bad_numbers_and_video_names_are_refused(scene, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["train", str(scene), "--out", str(tmp_path / "o"), "--frames", "0"])
    assert exit_info.value.code == 2
    assert "positive int" in capsys.readouterr().err
    assert main(["render", str(tmp_path), "--video", "orbit.avi", "--device", "cpu"]) == 2
    assert ".mp4 or .gif" in one_line_error(capsys)


def test_output_files_are_vetted_before_the_run_is_loaded(tmp_path, capsys):
    run = tmp_path / "run"  # no checkpoint: any loading would fail with another message
    (run / "taken.ply").mkdir(parents=True)
    (run / "file").write_text("")
    cases = [(["export", str(run), "--mesh", "taken.ply"], "--mesh taken.ply: is a folder"),
             (["export", str(run), "--points", "file/p.ply"], "folder " + str(run / "file") + " does not exist"),
             (["export", str(run), "--mesh", "x" * 300 + ".ply"], "longer than the file system takes"),
             (["render", str(run), "--video", "taken.ply"], "expected a .mp4 or .gif path"),
             (["render", str(run), "--video", "file/v.mp4"], "does not exist"),
             (["render", str(run), "--dataparser-transforms", str(run / "file")],
              "maps a nerfstudio camera path, not --path orbit"),
             (["render", str(run), "--path", str(run / "file"), "--dataparser-transforms", str(run / "none.json")],
              "none.json: no such file")]
    for argv, message in cases:
        assert main([*argv, "--device", "cpu"]) == 2
        assert message in one_line_error(capsys), argv


def test_bad_settings_are_one_line_and_create_nothing(scene, tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["train", str(scene), "--out", str(out), "--set", "field.log2_hashmap_size=big"]) == 2
    assert "log2_hashmap_size takes an integer" in one_line_error(capsys)
    assert main(["train", str(scene), "--out", str(out), "--set", "no_such_setting=1"]) == 2
    assert "unknown setting" in one_line_error(capsys)
    assert main(["train", str(scene), "--out", str(out), "--resume", "--set", "lr=1e-3"]) == 2
    assert "keeps the settings in its checkpoint" in one_line_error(capsys)
    for setting, message in [("supersample=7", "supersample must be one of"), ("loss=l1", "loss must be one of"),
                             ("lr=0", "lr must be a number > 0"), ("distortion_weight=-1", "distortion_weight must be a number ≥ 0"),
                             ("distortion_spacing=metres", "distortion_spacing must be one of world, normalised"),
                             ("field.n_features_per_level=3", "n_features_per_level must be 1, 2, 4 or 8")]:
        assert main(["train", str(scene), "--out", str(out), "--device", "cpu", "--set", setting]) == 2
        assert message in one_line_error(capsys)
    assert not out.exists()


def test_eval_of_a_missing_folder_creates_nothing(tmp_path, capsys):
    assert main(["eval", str(tmp_path / "missing"), "--device", "cpu"]) == 2
    one_line_error(capsys)
    assert not (tmp_path / "missing").exists()


def test_camera_refinement_reports_its_corrections_and_refuses_contracted_scenes(scene, tmp_path, capsys):
    out = tmp_path / "refined"
    assert main(["train", str(scene), "--out", str(out), "--steps", "10", "--no-video", "--set", "camera_refinement=true",
                 "--set", "field.appearance_dim=4", *FAST]) == 0
    captured = capsys.readouterr()
    assert "camera refinement: rotations" in captured.err
    assert f"refined poses: {out / 'transforms_refined.json'}" in captured.err
    refined = load_scene(out / "transforms_refined.json")  # trains like the scene, on the refined poses
    assert sorted(refined.train.names + refined.test.names) == sorted(load_scene(scene).train.names)
    assert "each view's appearance code and pose fitted on its left half" in captured.out
    assert main(["train", str(scene), "--out", str(tmp_path / "contracted"), "--steps", "10", "--no-video",
                 "--set", "camera_refinement=true", "--set", "contraction=l2", *FAST]) == 2
    assert "camera_refinement needs a bounded scene" in one_line_error(capsys)
    assert not (tmp_path / "contracted").exists()


def test_cpu_training_gets_the_cpus_sizes_unless_set(scene, tmp_path, capsys):
    out = tmp_path / "cpu"
    assert main(["train", str(scene), "--out", str(out), "--steps", "3", "--no-video", *FAST]) == 0
    assert "table 2^16 per level" in capsys.readouterr().err
    saved = torch.load(out / "checkpoint.pt", weights_only=False)["train_config"]
    assert saved["grid_resolution"] == 64 and saved["field"]["log2_hashmap_size"] == 16
    assert main(["train", str(scene), "--out", str(tmp_path / "set"), "--steps", "3", "--no-video",
                 "--set", "field.log2_hashmap_size=14", "--set", "grid_resolution=32", *FAST]) == 0
    assert "table 2^14 per level" in capsys.readouterr().err


def test_a_run_inside_its_scene_folder_is_refused(scene, capsys):
    for out in (scene, scene / "run"):
        assert main(["train", str(scene), "--out", str(out), "--steps", "1", "--device", "cpu"]) == 2
        assert "would be written into the dataset" in one_line_error(capsys)
    assert not (scene / "run").exists() and not (scene / "checkpoint.pt").exists()


def test_a_base_resolution_above_the_finest_level_is_refused(scene, tmp_path, capsys):
    argv = ["train", str(scene), "--out", str(tmp_path / "o"), "--steps", "1", "--device", "cpu"]
    assert main([*argv, "--set", "field.base_resolution=4096"]) == 2  # the finest level picked: about 64
    assert "field.base_resolution 4096 is above the finest level's" in one_line_error(capsys)
    assert main([*argv, "--set", "field.base_resolution=64", "--set", "field.finest_resolution=32"]) == 2
    assert "the levels would grow coarser" in one_line_error(capsys)
    assert not (tmp_path / "o").exists()


def test_the_demos_resume_hint_names_its_output_folder(tmp_path, capsys):
    from argparse import Namespace
    from types import SimpleNamespace

    from ngp_warp.cli.common import _train

    class Interrupted:
        step_count = 7

        def train(self, **_):
            raise KeyboardInterrupt

    folder = SimpleNamespace(path=tmp_path / "demo", claimed=True)
    with pytest.raises(KeyboardInterrupt):  # the demo's args have no --resume
        _train(Interrupted(), lambda: None, folder, Namespace(quiet=True, checkpoint_every=300.0),
               tmp_path / "demo" / "scene")
    hint = f"ngp-warp train {tmp_path / 'demo' / 'scene'} --out {tmp_path / 'demo'} --resume"
    assert hint in capsys.readouterr().err


@pytest.mark.skipif(shutil.which("ngp-warp") is None, reason="needs the installed ngp-warp command")
@pytest.mark.parametrize("after", [0.3, 1.0])
def test_ctrl_c_while_the_modules_load_is_one_line(after):
    command = subprocess.Popen([shutil.which("ngp-warp"), "bench", "--quick", "--device", "cpu"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(after)  # the imports take seconds: the press lands while they load
    command.send_signal(signal.SIGINT)
    _, err = command.communicate(timeout=120)
    assert command.returncode == 130 and err.strip().splitlines()[-1] == "ngp-warp: interrupted", err
    assert "Traceback" not in err


def test_the_program_ends_with_its_output_flushed_and_its_exit_code(tmp_path):
    scene = write_demo_scene(tmp_path / "demo", width=16, height=16, n_train=6, n_test=1, supersample=1)
    program = [sys.executable, "-m", "ngp_warp.cli"]  # as the ngp-warp script: ngp_warp.cli.run
    buffered = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}  # output to a pipe waits in a buffer
    done = subprocess.run([*program, "train", str(scene), "--out", str(tmp_path / "run"), "--steps", "2",
                           "--device", "cpu", "--no-video", "--quiet"], capture_output=True, text=True, timeout=600,
                          env=buffered)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.rstrip().splitlines()[-1].startswith("wrote ")  # its last line, flushed before the end
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["steps"] == 2
    assert (tmp_path / "run" / "checkpoint.pt").stat().st_size > 0
    mistake = subprocess.run([*program, "eval", str(tmp_path / "no run")], capture_output=True, text=True, timeout=300,
                             env=buffered)
    assert mistake.returncode == 2 and mistake.stdout == ""
    assert mistake.stderr.startswith("ngp-warp: error: ") and mistake.stderr.count("\n") == 1, mistake.stderr
