"""``ngp-warp bench``."""

from __future__ import annotations

from ngp_warp.cli.common import resolve_device

def cmd_bench(args) -> None:
    from ngp_warp.outputs.bench import run_kernel_bench

    run_kernel_bench(resolve_device(args.device), quick=args.quick)
