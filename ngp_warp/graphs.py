"""CUDA graphs for the no-gradient density pass of a training step, whose size varies.

The pass before pruning evaluates σ at every marched sample: about a dozen small launches whose
host cost, not their GPU time, limits a step. :class:`GraphedDensity` pads the positions to a
bucket size (at most 1/16 larger), replays a graph captured once per bucket (all buckets share
one memory pool) and returns a copy of the first rows.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

_MIN_BUCKET = 1 << 12


def bucket_size(n: int) -> int:
    """The smallest multiple of 2^(e-4) that is ≥ n, for 2^e ≤ n < 2^(e+1) (16 buckets per
    octave), and of 4096."""
    step = max(_MIN_BUCKET, 1 << max(0, n.bit_length() - 5))
    return -(-n // step) * step


class GraphedDensity:
    """``fn(positions [N, 3]) → σ [N]`` (no gradient) replayed as CUDA graphs per bucket size."""

    def __init__(self, fn: Callable[[torch.Tensor], torch.Tensor]):
        self.fn = fn
        self.pool = None
        self.positions: torch.Tensor | None = None  # static input, grown as needed
        self.graphs: dict[int, tuple[torch.cuda.CUDAGraph, torch.Tensor]] = {}
        self.side: torch.cuda.Stream | None = None  # warm-up stream of every capture

    @torch.no_grad()
    def __call__(self, positions: torch.Tensor) -> torch.Tensor:
        n = positions.shape[0]
        size = bucket_size(n)
        if self.positions is None or self.positions.shape[0] < size:
            # A larger input buffer moves every captured input: start over, with a new pool
            # (torch frees a pool with its last graph).
            self.graphs.clear()
            self.pool = None
            self.positions = torch.zeros(2 * size, 3, device=positions.device)
        self.positions[:n].copy_(positions)
        entry = self.graphs.get(size)
        if entry is None:
            entry = self.graphs[size] = self._capture(size)
        graph, sigmas = entry
        graph.replay()
        return sigmas[:n].clone()

    def _capture(self, size: int) -> tuple[torch.cuda.CUDAGraph, torch.Tensor]:
        inp = self.positions[:size]
        if self.side is None:  # one stream, so ngp_warp._wp caches one Warp stream for it
            self.side = torch.cuda.Stream(device=inp.device)
        self.side.wait_stream(torch.cuda.current_stream(inp.device))
        with torch.cuda.stream(self.side):  # warm-up off the capture (as torch's docs ask)
            self.fn(inp)
        torch.cuda.current_stream(inp.device).wait_stream(self.side)
        if self.pool is None:
            self.pool = torch.cuda.graph_pool_handle()
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph, pool=self.pool):
            sigmas = self.fn(inp)
        return graph, sigmas
