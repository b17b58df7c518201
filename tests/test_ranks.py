"""``--gpus N``: the command line read without loading torch, the ranks started and watched
(exit codes, a failed rank stopping the rest), and one line for a mistake every rank makes."""

import os
import signal
import subprocess
import sys
import threading
import time

import pytest

from ngp_warp.cli import ranks


def test_the_command_line_loads_without_torch_or_warp():
    code = "import sys, ngp_warp.cli; print(sorted(m for m in ('torch', 'warp') if m in sys.modules))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == "[]", done.stderr[-2000:]


@pytest.mark.parametrize("argv, asked, rest", [
    (["train", "s", "--gpus", "2", "--out", "o"], 2, ["train", "s", "--out", "o"]),
    (["fit-many", "m", "--gpus=3"], 3, ["fit-many", "m"]),
    (["train", "s", "--gpu", "4"], 4, ["train", "s"]),  # argparse's prefixes of --gpus
    (["train", "s", "--gpus", "two"], 1, ["train", "s"]),  # not a number: the parser says so
    (["eval", "r", "--gpus", "2"], 1, ["eval", "r"]),  # no --gpus there: the parser says so
    (["train", "s", "--gpus"], 1, ["train", "s", "--gpus"]),
    (["train", "s", "--gpus", "\u00b2"], 1, ["train", "s"]),  # a digit, not a number
    (["train", "s", "--gpus", "4", "--gpus=2"], 2, ["train", "s"]),  # the last, as argparse
    (["train", "s"], 1, ["train", "s"]),
])
def test_gpus_is_read_and_left_out_of_the_ranks_command_line(argv, asked, rest):
    assert ranks.ranks_asked(argv) == asked and ranks.without_gpus(argv) == rest


RANK_SCRIPT = """
import os, sys, time
rank, world = os.environ["RANK"], os.environ["WORLD_SIZE"]
assert os.environ["LOCAL_RANK"] == rank and os.environ["MASTER_ADDR"] == "127.0.0.1"
assert int(os.environ["MASTER_PORT"]) > 0
codes = sys.argv[1].split(",")
if codes[int(rank)] == "hang":
    time.sleep(120)
sys.exit(int(codes[int(rank)]))
"""


@pytest.mark.parametrize("codes, expected", [("0,0", 0), ("2,2", 2), ("0,3", 1), ("2,0", 2), ("hang,5", 1)])
def test_the_launch_returns_what_the_ranks_did_and_stops_them_at_a_failure(codes, expected):
    start = time.monotonic()
    assert ranks.launch(2, [codes], command=[sys.executable, "-c", RANK_SCRIPT]) == expected
    assert time.monotonic() - start < 60  # a hanging rank is stopped once the other fails


@pytest.mark.parametrize("local_rank, reported", [("0", True), ("1", False)])
def test_a_mistake_in_the_arguments_is_reported_by_the_first_rank_alone(monkeypatch, capsys, tmp_path, local_rank,
                                                                          reported):
    from ngp_warp.cli import main

    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", local_rank)
    monkeypatch.setenv("LOCAL_RANK", local_rank)
    with pytest.raises(SystemExit) as done:
        main(["train", str(tmp_path / "scene"), "--out", str(tmp_path / "o"), "--steps", "0"])
    err = capsys.readouterr().err
    assert done.value.code == 2
    assert ("argument --steps: expected a positive int, got '0'" in err) == reported and (err == "") != reported


def test_a_mistake_in_the_arguments_is_one_line_under_gpus(tmp_path):
    command = [sys.executable, "-m", "ngp_warp.cli", "train", str(tmp_path / "scene"), "--out", str(tmp_path / "o"),
               "--gpus", "2", "--device", "cpu", "--steps", "0"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=300)
    errors = [line for line in done.stderr.splitlines() if "error:" in line]
    assert done.returncode == 2 and errors == ["ngp-warp train: error: argument --steps: expected a positive int, "
                                               "got '0'"], done.stderr[-2000:]
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signal_to_the_launch_reaches_every_rank(monkeypatch, sig, code):
    monkeypatch.setattr(ranks, "GRACE_SECONDS", 20.0)
    timer = threading.Timer(1.0, os.kill, (os.getpid(), sig))
    start = time.monotonic()
    timer.start()
    try:
        returned = ranks.launch(2, ["hang,hang"], command=[sys.executable, "-c", RANK_SCRIPT])
    finally:
        timer.cancel()  # never a signal to this process after the launch has ended
    assert returned == code
    assert time.monotonic() - start < 15  # the ranks ended on the signal passed on, not the kill after the grace


@pytest.mark.skipif((os.cpu_count() or 1) > 8, reason="starts one process more than this machine has cores")
def test_more_ranks_than_cores_is_one_line_from_rank_zero(tmp_path):
    n = (os.cpu_count() or 1) + 1
    command = [sys.executable, "-m", "ngp_warp.cli", "train", str(tmp_path / "scene"), "--out", str(tmp_path / "o"),
               "--gpus", str(n), "--device", "cpu", "--steps", "1"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=300)
    errors = [line for line in done.stderr.splitlines() if "error:" in line]
    assert done.returncode == 2 and errors == [f"ngp-warp: error: --gpus {n}: this machine has {os.cpu_count()} CPU "
                                               f"cores, too few for {n} CPU processes"], done.stderr[-2000:]
