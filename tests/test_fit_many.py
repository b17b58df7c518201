"""ngp-warp fit-many: 3 tiny scenes over 2 gloo ranks (through --gpus), a rerun that
skips them, an interrupted scene resumed, two nodes on one host (one of them killed), and bad
manifests as one line; two single-GPU nodes where a host has two GPUs."""

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ngp_warp.cli import fit_many, main
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


def _single_gpu_nodes(args: list[str], rdzv_id: str) -> list[subprocess.CompletedProcess]:
    """Run ``ngp-warp ARGS`` as two torchrun nodes of one process each on this host, node i
    seeing GPU i alone (as on two machines of one GPU), and wait for both."""
    node = [sys.executable, "-m", "torch.distributed.run", "--nnodes", "2", "--nproc-per-node", "1",
            "--rdzv-backend", "c10d", "--rdzv-endpoint", f"127.0.0.1:{_free_port()}", "--rdzv-id", rdzv_id,
            "-m", "ngp_warp.cli", *args]
    nodes = [subprocess.Popen(node, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                              env={**os.environ, "CUDA_VISIBLE_DEVICES": str(i)}) for i in range(2)]
    try:
        outputs = [p.communicate(timeout=400) for p in nodes]
    finally:  # a node that hangs must not outlive the test
        for p in nodes:
            _kill_tree(p.pid)
            p.wait()
    assert [p.returncode for p in nodes] == [0, 0], outputs[0][1][-2000:] + outputs[1][1][-2000:]
    return [subprocess.CompletedProcess(node, p.returncode, *o) for p, o in zip(nodes, outputs)]


@pytest.mark.cuda
@pytest.mark.slow
def test_two_single_gpu_nodes_on_one_host_train_one_scene_and_share_many(tmp_path):
    import torch
    if torch.cuda.device_count() < 2:
        pytest.skip("needs two CUDA GPUs")
    gpu = ["--device", "cuda", "--quiet", "--no-video"]
    for i, name in enumerate(["chair", "mug", "lamp"]):  # rendered on the GPU: a GPU machine may lack Warp's CPU compiler
        write_demo_scene(tmp_path / "scenes" / name, width=12, height=12, n_train=4, n_test=1, seed=i, supersample=1,
                         device="cuda")
    scene = tmp_path / "scenes" / "chair"
    done = _single_gpu_nodes(["train", str(scene), "--out", str(tmp_path / "one"), "--steps", "30", *gpu], "train-2x1")
    metrics = finished_metrics(tmp_path / "one")
    assert metrics["steps"] == 30 and metrics["device"].startswith("cuda")
    assert sum("PSNR" in d.stdout for d in done) == 1  # rank 0 alone evaluates and reports

    out = tmp_path / "many"
    _single_gpu_nodes(["fit-many", str(tmp_path / "scenes" / "*"), "--out", str(out), "--steps", "20", *gpu],
                      "fit-many-2x1")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ranks"] == 2 and sorted(r["rank"] for r in summary["per_rank"]) == [0, 1]
    assert sum(r["scenes"] for r in summary["per_rank"]) == 3
    assert all(r["status"] == "trained" and r["steps"] == 20 for r in summary["scenes"])


def _kill_tree(pid: int) -> None:
    """SIGKILL process ``pid`` and every descendant (torchrun starts its workers in sessions of
    their own, so its process group is not enough); Linux's /proc."""
    children = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError, ValueError, IndexError):
            fields = stat.read_text().rsplit(")", 1)[1].split()
            children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    tree, todo = [], [pid]
    while todo:
        tree.append(todo.pop())
        todo.extend(children.get(tree[-1], []))
    for p in tree:
        with contextlib.suppress(ProcessLookupError):
            os.kill(p, signal.SIGKILL)


@pytest.mark.slow
def test_a_node_that_dies_leaves_finished_scenes_and_a_rerun_fits_the_rest(tmp_path):
    """Two single-process nodes share four scenes; once a scene is finished the node holding the
    rendezvous store is killed (SIGKILL, its whole process tree). The other loses the queue and
    stops; every scene finished so far keeps a complete metrics.json, and the same command run
    again (one process) fits only the rest. (A survivor that holds the store fits every scene left,
    which would leave nothing to rerun.)"""
    root = tmp_path / "many"
    for i, name in enumerate(["chair", "mug", "lamp", "cup"]):
        write_demo_scene(root / "scenes" / name, width=12, height=12, n_train=4, n_test=1, seed=i, supersample=1)
    (root / "manifest.txt").write_text("scenes/*\n")
    out = tmp_path / "out"
    args = ["fit-many", str(root / "manifest.txt"), "--out", str(out), "--steps", "40", *TINY]
    endpoint = f"127.0.0.1:{_free_port()}"

    def node(is_host: int) -> list[str]:  # the host node holds the rendezvous store the queue lives in
        return [sys.executable, "-m", "torch.distributed.run", "--nnodes", "2", "--nproc-per-node", "1",
                "--rdzv-backend", "c10d", "--rdzv-endpoint", endpoint, "--rdzv-id", "fit-many-kill",
                "--rdzv-conf", f"is_host={is_host}", "-m", "ngp_warp.cli", *args]

    env = {**os.environ, "OMP_NUM_THREADS": "1"}  # two nodes on one host's cores
    nodes = [subprocess.Popen(node(is_host), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env,
                              start_new_session=True) for is_host in (0, 1)]
    try:
        start = time.monotonic()
        while not any(finished_metrics(d) for d in out.glob("*") if d.is_dir()):
            assert time.monotonic() - start < 240 and all(p.poll() is None for p in nodes), "no scene finished"
            time.sleep(0.1)
        _kill_tree(nodes[1].pid)  # the host node: torchrun's agent, its store and its worker
        with contextlib.suppress(subprocess.TimeoutExpired):  # torchrun's agent may wait for the dead one's
            nodes[0].wait(timeout=90)
    finally:
        for p in nodes:
            _kill_tree(p.pid)
            p.wait()
    finished = {d.name: (d / "metrics.json").stat().st_mtime_ns for d in out.glob("*") if finished_metrics(d)}
    assert 1 <= len(finished) <= 3
    assert main(args) == 0
    rows = {r["scene"]: r for r in json.loads((out / "summary.json").read_text())["scenes"]}
    assert sorted(rows) == ["chair", "cup", "lamp", "mug"] and all(r["steps"] == 40 for r in rows.values())
    assert {n for n, r in rows.items() if r["status"] == "skipped"} == set(finished)
    assert all((out / n / "metrics.json").stat().st_mtime_ns == stamp for n, stamp in finished.items())


class FakeStore:
    """The store calls _all_ranks makes; ``alive`` ranks raise their counter at every read."""

    def __init__(self, alive=()):
        self.values, self.alive = {}, set(alive)

    def set(self, key, value):
        self.values[key] = value.encode() if isinstance(value, str) else value

    def check(self, keys):
        return all(k in self.values for k in keys)

    def get(self, key):
        return self.values[key]

    def add(self, key, amount):
        rank = int(key.rsplit("/", 1)[1])
        self.values[key] = self.values.get(key, 0) + amount + (rank in self.alive)
        return self.values[key]


def test_rank_zero_collects_the_ranks_that_post_and_names_the_silent_one_lost(monkeypatch):
    import torch.distributed as dist

    store = FakeStore(alive={1})
    store.set(fit_many.RESULT_KEY + "1", json.dumps([[{"scene": "mug", "rank": 1}], 3.0]))
    monkeypatch.setattr(dist, "is_initialized", lambda: True)
    monkeypatch.setattr(dist, "get_rank", lambda: 0)
    monkeypatch.setattr(dist, "get_world_size", lambda: 3)
    monkeypatch.setattr(dist.distributed_c10d, "_get_default_store", lambda: store)
    monkeypatch.setattr(fit_many, "LOST_AFTER_SECONDS", 0.5)
    start = time.monotonic()
    rows, busy, lost = fit_many._all_ranks([{"scene": "chair", "rank": 0}], 2.0)
    assert [r["scene"] for r in rows] == ["chair", "mug"] and busy == [2.0, 3.0, None] and lost == [2]
    assert 0.5 < time.monotonic() - start < 5
    store = FakeStore(alive={2})  # rank 2 still beating: waited for, not lost, until it posts
    monkeypatch.setattr(dist.distributed_c10d, "_get_default_store", lambda: store)
    store.set(fit_many.RESULT_KEY + "1", json.dumps([[], 1.0]))
    reads = []

    def add(key, amount, add=store.add):
        reads.append(key)
        if len(reads) == 10:  # after 10 reads (2 s, 4 times the limit) rank 2 posts
            store.set(fit_many.RESULT_KEY + "2", json.dumps([[{"scene": "lamp", "rank": 2}], 4.0]))
        return add(key, amount)

    monkeypatch.setattr(store, "add", add)
    rows, busy, lost = fit_many._all_ranks([], 2.0)
    assert [r["scene"] for r in rows] == ["lamp"] and busy == [2.0, 1.0, 4.0] and lost == []


def test_a_lost_store_is_one_line(monkeypatch):
    import torch.distributed as dist

    class GoneStore:
        def add(self, key, amount):
            raise dist.DistNetworkError("Broken pipe")

    monkeypatch.setattr(dist, "is_initialized", lambda: True)
    monkeypatch.setattr(dist.distributed_c10d, "_get_default_store", lambda: GoneStore())
    with pytest.raises(FitManyError, match=r"^lost the rendezvous store \(Broken pipe: its node died\?\); the scenes "
                                           r"finished are kept, and the same command run again fits the rest$"):
        next(fit_many.claimed_scenes([0, 1, 2]))


def test_scenes_are_claimed_largest_first(tmp_path, monkeypatch):
    import torch.distributed as dist

    scenes = []
    for name, size in [("small", 10), ("large", 300), ("medium", 50), ("twin", 50)]:
        (tmp_path / name / "images").mkdir(parents=True)
        (tmp_path / name / "images" / "a.png").write_bytes(b"x" * size)
        scenes.append(tmp_path / name)
    order = fit_many.largest_first(scenes)
    assert [scenes[i].name for i in order] == ["large", "medium", "twin", "small"]
    assert list(fit_many.claimed_scenes(order)) == order  # outside a process group: all, in order

    class CounterStore:  # two ranks sharing the queue's counter
        def __init__(self):
            self.count = 0

        def add(self, key, amount):
            self.count += amount
            return self.count

    store = CounterStore()
    monkeypatch.setattr(dist, "is_initialized", lambda: True)
    monkeypatch.setattr(dist.distributed_c10d, "_get_default_store", lambda: store)
    rank0, rank1 = fit_many.claimed_scenes(order), fit_many.claimed_scenes(order)
    claims = [next(rank0), next(rank1), next(rank1), next(rank0)]
    assert claims == order and list(rank0) == [] and list(rank1) == []


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
