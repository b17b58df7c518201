"""benchmarks/bench_captures.py's summary of several runs and its table."""

import pytest

from benchmark_scripts import load_benchmark

bench_captures = load_benchmark("bench_captures")


def run(whole: float, contraction: str) -> dict:
    return {"psnr_nearest_code": whole, "psnr_mean_code": whole - 0.5, "psnr": whole + 0.25, "ssim": 0.9,
            "steps": 1000, "train_seconds": 4.0, "train_samples_per_ray": 12.0, "contraction": contraction}


def test_the_summary_counts_the_contraction_each_run_used_where_a_probe_chose_differently():
    mixed = bench_captures.summary([run(33.0, "none"), run(31.0, "l2"), run(32.0, "none")])
    assert mixed["contraction"] == "none ×2, l2 ×1" and mixed["runs"] == 3
    assert mixed["whole"] == pytest.approx(32.0) and mixed["whole_sd"] == pytest.approx(1.0)
    assert mixed["right"] == pytest.approx(32.25) and mixed["ms"] == pytest.approx(4.0)
    same = bench_captures.summary([run(30.0, "l2"), run(30.5, "l2")])
    assert same["contraction"] == "l2"
    row = bench_captures.table([("unbounded-colmap", "defaults", mixed)]).splitlines()[-1]
    assert row.startswith("| unbounded-colmap | defaults | none ×2, l2 ×1 | 32.00 ± 1.00 | 31.50 | 32.25 |")
    failed = bench_captures.summary([{"error": "out of memory"}])
    assert "failed: out of memory" in bench_captures.table([("room-colmap", "defaults", failed)])


def test_a_compared_setting_is_scored_against_the_defaults_of_the_same_seeds():
    base = [run(32.0, "none"), run(31.0, "none"), {"error": "failed"}]
    compared = [run(31.5, "none"), run(31.0, "none"), run(40.0, "none")]  # the third has no pair
    d = bench_captures.paired(compared, base)
    assert d["pairs"] == 2 and d["delta"] == pytest.approx(-0.25) and d["delta_sd"] == pytest.approx(0.3535534)
    uncoded = {k: v for k, v in run(30.0, "none").items() if k not in ("psnr_nearest_code", "psnr_mean_code")}
    assert bench_captures.paired([uncoded], [run(29.0, "none")])["delta"] == pytest.approx(30.25 - 29.0)
    assert bench_captures.paired([{"error": "x"}], base) == {"pairs": 0}
    lines = bench_captures.pair_table([("demo-colmap", "field.n_levels=8", d),
                                       ("fox", "field.n_levels=8", {"pairs": 0})]).splitlines()
    assert lines[2] == "| demo-colmap | field.n_levels=8 | -0.25 ± 0.35 | 2 |"
    assert lines[3] == "| fox | field.n_levels=8 |  | 0 |"


def test_each_held_out_view_is_tabled_with_its_mean_and_lowest_run():
    def views(*scores):
        return {**run(31.0, "none"), "per_image": [{"image": f"/x/images/{i:04d}.jpg", "psnr": p}
                                                   for i, p in enumerate(scores)]}
    rows = [("fox", "defaults", [views(31.0, 25.0), views(33.0, 31.0), {"error": "x"}]),
            ("lego-colmap", "defaults", [views(*range(20))])]  # more views than the table shows
    lines = bench_captures.view_table(rows).splitlines()
    assert len(lines) == 3
    assert lines[2] == "| fox | defaults | 2 | 0000 32.00 (31.00), 0001 28.00 (25.00) |"
    assert bench_captures.view_table(rows[1:]) == ""


def test_runs_on_several_gpus_each_hold_a_gpu_of_their_own_and_keep_their_order(monkeypatch):
    import threading
    import time
    from argparse import Namespace

    holding, lock, seen = set(), threading.Lock(), []

    def fake_train(scene, out, args, seed, settings, gpu=None):
        with lock:
            assert gpu not in holding  # no two runs at once on one GPU
            holding.add(gpu)
            seen.append(gpu)
        time.sleep(0.02)
        with lock:
            holding.remove(gpu)
        return {"seed": seed}

    monkeypatch.setattr(bench_captures, "train", fake_train)
    jobs = [(None, None, seed, []) for seed in range(7)]
    ids = ["4", "5", "7", "2"]  # CUDA_VISIBLE_DEVICES's ids: the first three are used
    assert bench_captures.train_all(jobs, Namespace(gpus=3, gpu_ids=ids)) == [{"seed": s} for s in range(7)]
    assert set(seen) == {"4", "5", "7"}
    assert bench_captures.train_all(jobs[:2], Namespace(gpus=1)) == [{"seed": 0}, {"seed": 1}]
    assert None in seen[-2:]  # one at a time: on the GPUs the command sees
