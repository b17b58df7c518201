"""CUDA graphs: :func:`capture_graph` for any fixed-size work on ngp_warp's ops, and
:class:`GraphedDensity` for the no-gradient density pass of a training step, whose size varies.

Work whose host cost exceeds its GPU time (many small launches, an autograd backward) runs at
device speed when replayed from a graph. ngp_warp's ops can be captured where they do not read
a size back to the host: :func:`ngp_warp.ray_marching` with ``capacity=`` and
``validate=False``, :func:`ngp_warp.composite` with ``validate=False`` (or ``composite_packed``)
with its backward, :func:`ngp_warp.prune_samples` with ``capacity=``, and the hash grid. A
stratified march draws its seed on the host, so its jitter repeats on every replay.

The pass before pruning evaluates σ at every marched sample: about a dozen small launches whose
host cost, not their GPU time, limits a step. :class:`GraphedDensity` pads the positions to a
bucket size (at most 1/16 larger), replays a graph captured once per bucket (all buckets share
one memory pool) and returns a copy of the first rows.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

_MIN_BUCKET = 1 << 12


def capture_graph(fn: Callable[[], object], device: torch.device | str, side: torch.cuda.Stream | None = None,
                  pool=None) -> tuple[torch.cuda.CUDAGraph, object]:
    """``fn()`` run once on a side stream (a warm-up, as torch's docs ask: kernels load, the
    allocator settles), then captured in a CUDA graph.

    Returns ``(graph, output)``: ``graph.replay()`` repeats ``fn``'s work on the tensors it read
    (change them in place between replays) and writes into the same ``output`` tensors. Pass
    ``side`` to reuse one warm-up stream (ngp_warp caches a Warp stream per torch stream) and
    ``pool`` to share a memory pool between graphs.
    """
    device = torch.device(device)
    side = side or torch.cuda.Stream(device=device)
    side.wait_stream(torch.cuda.current_stream(device))
    with torch.cuda.stream(side):
        fn()
    torch.cuda.current_stream(device).wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph, pool=pool):
        output = fn()
    return graph, output


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
        if self.pool is None:
            self.pool = torch.cuda.graph_pool_handle()
        return capture_graph(lambda: self.fn(inp), inp.device, self.side, self.pool)
