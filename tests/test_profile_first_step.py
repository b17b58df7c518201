"""benchmarks/profile_first_step.py: the first steps' loads and captures, counted and put back."""

import sys
import time

import pytest

import ngp_warp.ops.graphs as graphs
import ngp_warp.ops.render as render_op
from benchmark_scripts import load_benchmark
from data_fixtures import nerf_synthetic
from ngp_warp._warp_private import _probe

profile_first_step = load_benchmark("profile_first_step")


def test_a_tally_counts_only_the_slow_calls_and_starts_again_when_taken():
    tally = profile_first_step.Tally()
    slow = tally.wrap(lambda: time.sleep(0.01), slow=0.005)
    fast = tally.wrap(lambda: 1, slow=0.005)
    assert fast() == 1
    slow()
    slow()
    seconds, calls = tally.take()
    assert calls == 2 and 0.02 <= seconds < 1.0
    assert tally.take() == (0.0, 0)


def test_counting_puts_the_originals_back():
    module_class = type(_probe.module)
    load, capture = module_class.load, graphs.capture_graph
    loads, captures = profile_first_step.Tally(), profile_first_step.Tally()
    with pytest.raises(RuntimeError):
        with profile_first_step.counting(loads, captures):
            assert module_class.load is not load and graphs.capture_graph is not capture
            raise RuntimeError("a failed profile")
    assert module_class.load is load and graphs.capture_graph is capture


def test_prints_the_start_the_first_step_and_the_steps_after_it(tmp_path, capsys, monkeypatch):
    for name in ("ray_marching", "prune_samples"):  # profile_train_step's phase timers wrap these
        monkeypatch.setattr(render_op, name, getattr(render_op, name))
    nerf_synthetic(tmp_path / "scene", n_train=4, n_test=2, size=(24, 16))
    monkeypatch.setattr(sys, "argv", ["profile_first_step.py", str(tmp_path / "scene"), "--device", "cpu",
                                      "--steps", "10", "--cprofile", "5", "--set", "field.n_levels=4",
                                      "--set", "field.log2_hashmap_size=10", "--set", "target_samples=2048"])
    profile_first_step.main()
    out = capsys.readouterr().out
    first = next(line for line in out.splitlines() if line.startswith("first step: "))
    assert float(first.split()[2]) > 0
    for expected in ("start: import torch ", "| occupancy grid update | ", "| backward (autograd engine) | ",
                     "steps 2-11: ", "test view 24x16: first render ", "top 5 by cumulative time"):
        assert expected in out, expected
    with pytest.raises(SystemExit):
        monkeypatch.setattr(sys, "argv", ["profile_first_step.py", str(tmp_path / "scene"), "--steps", "3"])
        profile_first_step.main()
