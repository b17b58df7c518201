"""``ngp-warp bench``: the kernel throughput table on the CPU, smallest sizes."""

import math

from ngp_warp.outputs.bench import KernelBenchConfig
from ngp_warp.cli import main

OPS = ("encode fwd", "encode bwd", "encode fwd+bwd", "march", "composite fwd", "composite bwd", "march+fwd+bwd",
       "same, capacity")


def test_bench_quick_prints_the_table(capsys):
    assert main(["bench", "--quick", "--device", "cpu"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("device: cpu (")
    assert lines[1].split() == ["op", "N", "ms", "M", "items/s"]
    config = KernelBenchConfig.for_device("cpu", quick=True)
    rows = {}
    for line in lines[3:]:
        op, sep, numbers = line.partition("  ")
        if sep and op.strip() in OPS:
            rows[op.strip()] = numbers.split()
    assert sorted(rows) == sorted(OPS)
    for op, (n, ms, mps) in rows.items():
        n, ms, mps = int(n), float(ms), float(mps)
        assert 0 < ms and math.isfinite(ms) and 0 < mps and math.isfinite(mps), (op, ms, mps)
        assert math.isclose(mps, n / ms * 1e-3, rel_tol=0.05, abs_tol=0.01), (op, n, ms, mps)
        if op.startswith("encode"):
            assert n == config.points
        else:  # samples actually marched: about the target
            assert config.samples / 2 < n < config.samples * 2, (op, n)
