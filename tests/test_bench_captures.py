"""benchmarks/bench_captures.py's summary of several runs and its table."""

import importlib.util
from pathlib import Path

import pytest

_spec = importlib.util.spec_from_file_location("bench_captures",
                                               Path(__file__).parents[1] / "benchmarks" / "bench_captures.py")
bench_captures = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench_captures)


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
