"""ngp-warp fit-many: 3 tiny scenes over 2 gloo ranks (torchrun through --gpus), a rerun that
skips them, an interrupted scene resumed, and bad manifests as one line."""

import json
import socket
import subprocess
import sys

import pytest

from ngp_warp.cli import main
from ngp_warp.cli.fit_many import finished_metrics, read_manifest, FitManyError
from ngp_warp.data.scene import write_demo_scene

TINY = ["--device", "cpu", "--quiet", "--no-video", "--target-samples", "1024", "--set", "grid_resolution=16",
        "--set", "field.log2_hashmap_size=12", "--set", "field.n_levels=4", "--set", "field.hidden=16"]


@pytest.fixture(scope="module")
def manifest(tmp_path_factory):
    root = tmp_path_factory.mktemp("many")
    for i, name in enumerate(["chair", "mug", "lamp"]):
        write_demo_scene(root / "scenes" / name, width=12, height=12, n_train=4, n_test=1, seed=i, supersample=1)
    path = root / "manifest.txt"
    path.write_text("# three tiny scenes\nscenes/chair\n\nscenes/[ml]*\n")
    return path


def one_line_error(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert err and err[-1].startswith("ngp-warp: error: ") and not any("Traceback" in e for e in err), err
    return err[-1]


def test_manifest_lines_globs_and_comments(manifest):
    assert [p.name for p in read_manifest(str(manifest))] == ["chair", "lamp", "mug"]
    assert [p.name for p in read_manifest(str(manifest.parent / "scenes" / "*"))] == ["chair", "lamp", "mug"]


@pytest.mark.parametrize("text, message", [
    ("scenes/sofa\n", "scene folder"), ("# nothing\n", "names no scene folders"),
    ("scenes/chair\nscenes/../scenes/chair\n", "two scenes are named 'chair'")])
def test_bad_manifests_are_one_line_and_write_nothing(manifest, tmp_path, capsys, text, message):
    bad = manifest.parent / "bad.txt"
    bad.write_text(text)
    with pytest.raises(FitManyError, match=message):
        read_manifest(str(bad))
    assert main(["fit-many", str(bad), "--out", str(tmp_path / "out"), "--steps", "1", *TINY]) == 2
    assert message in one_line_error(capsys)
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_two_ranks_fit_three_scenes_then_a_rerun_skips_them(manifest, tmp_path, capsys):
    out = tmp_path / "out"
    command = [sys.executable, "-m", "ngp_warp.cli", "fit-many", str(manifest), "--out", str(out), "--steps", "4",
               "--gpus", "2", *TINY]
    done = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ranks"] == 2 and [r["scene"] for r in summary["scenes"]] == ["chair", "lamp", "mug"]
    per_rank = summary["per_rank"]  # the queue hands every scene out once
    assert [r["rank"] for r in per_rank] == [0, 1] and sum(r["scenes"] for r in per_rank) == 3
    assert all(r["busy_seconds"] > 0 and 0 <= r["idle_seconds"] <= summary["wall_seconds"] for r in per_rank)
    assert sorted(r["rank"] for r in summary["scenes"]) == sorted(
        k for r in per_rank for k in [r["rank"]] * r["scenes"])
    assert all(r["status"] == "trained" and r["steps"] == 4 and r["psnr"] > 0 for r in summary["scenes"])
    assert "chair" in done.stdout and "3 fitted" in done.stdout
    for name in ("chair", "lamp", "mug"):
        assert finished_metrics(out / name)["steps"] == 4 and (out / name / "checkpoint.pt").is_file()
    stamps = {name: (out / name / "metrics.json").stat().st_mtime_ns for name in ("chair", "lamp", "mug")}

    # a rerun (one process) skips the finished scenes and resumes an interrupted one to the budget
    (out / "mug" / "metrics.json").unlink()
    assert main(["fit-many", str(manifest), "--out", str(out), "--steps", "6", *TINY]) == 0
    rows = {r["scene"]: r for r in json.loads((out / "summary.json").read_text())["scenes"]}
    assert [rows[n]["status"] for n in ("chair", "lamp", "mug")] == ["skipped", "skipped", "resumed"]
    assert rows["chair"]["steps"] == 4 and rows["mug"]["steps"] == 6
    assert (out / "chair" / "metrics.json").stat().st_mtime_ns == stamps["chair"]
    assert "2 skipped as finished" in capsys.readouterr().out


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_two_nodes_on_one_host_share_the_scenes_through_the_rendezvous(manifest, tmp_path):
    out = tmp_path / "out"
    node = [sys.executable, "-m", "torch.distributed.run", "--nnodes", "2", "--nproc-per-node", "1",
            "--rdzv-backend", "c10d", "--rdzv-endpoint", f"127.0.0.1:{_free_port()}", "--rdzv-id", "fit-many-test",
            "-m", "ngp_warp.cli", "fit-many", str(manifest), "--out", str(out), "--steps", "3", *TINY]
    nodes = [subprocess.Popen(node, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    outputs = [p.communicate(timeout=300) for p in nodes]
    assert [p.returncode for p in nodes] == [0, 0], outputs[0][1][-2000:] + outputs[1][1][-2000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ranks"] == 2 and sum(r["scenes"] for r in summary["per_rank"]) == 3
    assert all(r["status"] == "trained" and r["steps"] == 3 for r in summary["scenes"])


def test_incomplete_metrics_are_not_finished(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    assert finished_metrics(run) is None
    (run / "metrics.json").write_text('{"psnr": 20.0, "steps": 5')  # cut short
    assert finished_metrics(run) is None
    record = {"psnr": 20.0, "steps": 5, "train_seconds": 1.0, "n_test_images": 2, "per_image": [{}]}
    (run / "metrics.json").write_text(json.dumps(record))
    assert finished_metrics(run) is None
    (run / "metrics.json").write_text(json.dumps({**record, "per_image": [{}, {}]}))
    assert finished_metrics(run)["steps"] == 5
