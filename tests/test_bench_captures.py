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
