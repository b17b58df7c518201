"""Glue between torch tensors and Warp kernels: quiet init, devices, streams, launches.

Every op in ngp_warp launches its kernels through :func:`launch`, which

* runs on the device the tensors live on (``"cpu"`` or ``"cuda:N"``),
* on CUDA, runs on torch's *current* stream (the Warp stream wrapping it is cached),
* on the CPU, splits a 1-D launch into disjoint ranges run from a small thread pool.
  Warp's CPU backend runs one launch on one thread, but launches from several Python
  threads run in parallel (the GIL is released inside the launch).

Kernels launched through :func:`launch` take ``first: int`` as their first parameter and
handle item ``first + wp.tid()``; the item count is the launch dimension.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import torch
import warp as wp

_init_lock = threading.Lock()
_initialised = False


def init() -> None:
    """Initialise Warp once, without its banner or the no-driver warning on CPU machines."""
    global _initialised
    if _initialised:
        return
    with _init_lock:
        if _initialised:
            return
        wp.config.log_level = wp.LOG_ERROR
        # The native library prints a warning to fd 2 when no CUDA driver exists; hide it
        # only for the duration of init so real errors later still show.
        saved = os.dup(2)
        try:
            with open(os.devnull, "w") as devnull:
                os.dup2(devnull.fileno(), 2)
                wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        _initialised = True


def cuda_available() -> bool:
    """True when both torch and Warp can use a CUDA device."""
    init()
    return torch.cuda.is_available() and wp.get_cuda_device_count() > 0


def device_of(t: torch.Tensor) -> str:
    """Warp device name for a tensor's device."""
    if t.device.type == "cpu":
        return "cpu"
    if t.device.type == "cuda":
        return f"cuda:{t.device.index if t.device.index is not None else torch.cuda.current_device()}"
    raise ValueError(f"ngp_warp runs on CPU or CUDA tensors, got a tensor on {t.device}")


_streams: dict[int, wp.Stream] = {}


def current_stream(device: str) -> wp.Stream | None:
    """The Warp stream wrapping torch's current stream on ``device`` (None on CPU)."""
    if device == "cpu":
        return None
    ts = torch.cuda.current_stream(torch.device(device))
    s = _streams.get(ts.cuda_stream)
    if s is None:
        s = _streams[ts.cuda_stream] = wp.stream_from_torch(ts)
    return s


def to_wp(t: torch.Tensor, dtype=None) -> wp.array:
    """Zero-copy Warp view of a contiguous tensor (no Warp-side gradient buffer)."""
    return wp.from_torch(t, dtype=dtype, requires_grad=False)


def cpu_threads() -> int:
    """Threads used for CPU launches (``NGP_WARP_CPU_THREADS`` overrides the core count)."""
    env = os.environ.get("NGP_WARP_CPU_THREADS")
    if env:
        return max(1, int(env))
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)


_pool: ThreadPoolExecutor | None = None
_MIN_ITEMS_PER_THREAD = 2048


def _cpu_pool(n: int) -> ThreadPoolExecutor:
    global _pool
    if _pool is None or _pool._max_workers < n:
        _pool = ThreadPoolExecutor(max_workers=n, thread_name_prefix="ngp-warp-cpu")
    return _pool


def launch(kernel, n: int, inputs: list, device: str, align: int = 1) -> None:
    """Launch ``kernel(first, *inputs)`` over ``n`` items on ``device``.

    On CUDA this is one launch on torch's current stream. On the CPU the range is split
    into up to :func:`cpu_threads` disjoint chunks launched in parallel; every chunk boundary
    is a multiple of ``align``. Kernels whose items add to the same memory only within one
    aligned block of ``align`` items pass it, so that each block stays on one thread (Warp's
    CPU atomics are plain read-modify-writes).
    """
    if n <= 0:
        return
    if device != "cpu":
        wp.launch(kernel, dim=n, inputs=[0, *inputs], device=device, stream=current_stream(device))
        return
    align = max(1, align)
    n_threads = min(cpu_threads(), max(1, n // _MIN_ITEMS_PER_THREAD), -(-n // align))
    if n_threads == 1:
        wp.launch(kernel, dim=n, inputs=[0, *inputs], device="cpu")
        return
    bounds = [min(n, -(-(n * k // n_threads) // align) * align) for k in range(n_threads + 1)]
    pool = _cpu_pool(n_threads)
    futures = [
        pool.submit(wp.launch, kernel, dim=hi - lo, inputs=[lo, *inputs], device="cpu")
        for lo, hi in zip(bounds[:-1], bounds[1:])
        if hi > lo
    ]
    for f in futures:
        f.result()
