"""Glue between torch tensors and Warp kernels: quiet init, devices, streams, launches.

Every op in ngp_warp launches its kernels through :func:`launch`, which

* runs on the device the tensors live on (``"cpu"`` or ``"cuda:N"``),
* on CUDA, runs on torch's *current* stream (the Warp stream wrapping it is cached),
* on the CPU, splits a 1-D launch into disjoint ranges run from a small thread pool.
  Warp's CPU backend runs one launch on one thread, but launches from several Python
  threads run in parallel (the GIL is released inside the launch).

Kernels launched through :func:`launch` take ``first: int`` as their first parameter and
handle item ``first + wp.tid()``; the item count is the launch dimension. A launch replays a
``wp.Launch`` recorded once per kernel, device, block size and thread, writing the new
arguments into it in place; tensors are passed as they are and viewed with the kernel
parameter's dtype. That costs a few microseconds of Python per launch where ``wp.launch``
with ``wp.from_torch`` views costs tens, which matters for ops that take well under a
millisecond on a GPU. The replay relies on Warp internals, all of them in
``ngp_warp/_warp_private.py``, which checks them: should a Warp release change any, launches go
through the public ``wp.launch`` instead (same results, slower, one warning). There are no
per-call dtype or length checks: the public functions validate their inputs first.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import torch
import warp as wp

from ngp_warp import _warp_private as _private

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


init()  # on import: every module that launches kernels imports this one


def cuda_available() -> bool:
    """True when both torch and Warp can use a CUDA device."""
    return torch.cuda.is_available() and wp.get_cuda_device_count() > 0


def device_of(t: torch.Tensor) -> str:
    """Warp device name for a tensor's device."""
    if t.device.type == "cpu":
        return "cpu"
    if t.device.type == "cuda":
        return f"cuda:{t.device.index if t.device.index is not None else torch.cuda.current_device()}"
    raise ValueError(f"ngp_warp runs on CPU or CUDA tensors, got a tensor on {t.device}")


_streams: dict[int, wp.Stream] = {}
_cuda_index: dict[str, int] = {}


def current_stream(device: str) -> wp.Stream | None:
    """The Warp stream wrapping torch's current stream on ``device`` (None on CPU)."""
    if device == "cpu":
        return None
    index = _cuda_index.get(device)
    if index is None:
        index = _cuda_index[device] = torch.device(device).index or 0
    ts = torch.cuda.current_stream(index)
    s = _streams.get(ts.cuda_stream)
    if s is None:
        s = _streams[ts.cuda_stream] = wp.stream_from_torch(ts)
    return s


def to_wp(t: torch.Tensor, dtype=None) -> _private.Descriptor:
    """Zero-copy Warp view of a tensor (no gradient buffer), as an array descriptor that keeps
    ``t`` alive; :func:`launch` and ``wp.launch`` take it for an array parameter.

    ``dtype`` defaults to the tensor's scalar type; a vector dtype (``wp.vec3`` ...) consumes
    the trailing dimension. Mismatched dtypes or inner shapes raise ``RuntimeError``.
    """
    view = None if dtype is None or not _private.usable() else _private.view(dtype)
    if view is None or not _private.fits(t, view):
        return wp.from_torch(t, dtype=dtype, requires_grad=False, return_ctype=True)
    return _private.descriptor(t, view)


def cpu_threads() -> int:
    """Threads used for CPU launches (``NGP_WARP_CPU_THREADS`` overrides the core count)."""
    env = os.environ.get("NGP_WARP_CPU_THREADS")
    if env:
        if not env.strip().isdigit():
            raise ValueError(f"NGP_WARP_CPU_THREADS must be a positive integer, got {env!r}")
        return max(1, int(env))
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)


_pool: ThreadPoolExecutor | None = None
_pool_workers = 0
_MIN_ITEMS_PER_THREAD = 2048


def _cpu_pool(n: int) -> ThreadPoolExecutor:
    global _pool, _pool_workers
    if _pool is None or _pool_workers < n:
        _pool = ThreadPoolExecutor(max_workers=n, thread_name_prefix="ngp-warp-cpu")
        _pool_workers = n
    return _pool


_signatures: dict = {}
_local = threading.local()
_devices: dict[str, wp.Device] = {}


def _signature(kernel) -> _private.Signature:
    sig = _signatures.get(kernel)
    if sig is None:
        sig = _signatures[kernel] = _private.Signature(kernel)
    return sig


def _command(sig: _private.Signature, device: str, block_dim: int) -> _private.Command | None:
    """This thread's recorded launch of ``sig.kernel`` on ``device`` (loading, i.e. compiling,
    the module first); None when the recorded launch does not look as Warp 1.19's did."""
    commands = getattr(_local, "commands", None)
    if commands is None:
        commands = _local.commands = {}
    dev = _devices.get(device)
    if dev is None:
        dev = _devices[device] = wp.get_device(device)
    if dev.is_cpu:
        block_dim = 1  # as wp.launch resolves it on the CPU
    module_exec = _private.module_exec(sig.kernel, dev, block_dim)
    cmd = commands.get((sig.kernel, device, block_dim))
    if cmd is None or cmd.module_exec is not module_exec:  # new, or the module was rebuilt
        cmd = _private.Command(sig, dev, block_dim, module_exec)
        found = _private.launch_problems(cmd)
        if found:
            _private.report(found)
            return None
        commands[(sig.kernel, device, block_dim)] = cmd
    return cmd


def _public_launch(kernel, n: int, inputs: list, device: str, block_dim: int) -> None:
    """The whole launch through ``wp.launch`` (one CPU thread): the path taken when Warp's
    internals differ from those :mod:`ngp_warp._warp_private` relies on."""
    args = [0, *(v.detach() if isinstance(v, torch.Tensor) else v for v in inputs)]
    wp.launch(kernel, dim=n, inputs=args, device=device, stream=current_stream(device), block_dim=block_dim)


def launch(kernel, n: int, inputs: list, device: str, align: int = 1, block_dim: int = 256) -> None:
    """Launch ``kernel(first, *inputs)`` over ``n`` items on ``device``.

    ``inputs`` holds, per kernel parameter after ``first``: a tensor (viewed with the
    parameter's Warp dtype, see :func:`to_wp`), a Warp array or array descriptor, None for an
    unused array, a Python scalar, or a Warp struct instance. Each thread replays its own
    recorded launch of the kernel with the new arguments (no per-call ``wp.launch`` argument
    checks: callers validate).

    On CUDA this is one launch on torch's current stream. On the CPU the range is split
    into up to :func:`cpu_threads` disjoint chunks launched in parallel; every chunk boundary
    is a multiple of ``align``. Kernels whose items add to the same memory only within one
    aligned block of ``align`` items pass it, so that each block stays on one thread (Warp's
    CPU atomics are plain read-modify-writes). ``block_dim`` is the CUDA block size (Warp
    builds a module once per block size it is launched with): kernels with few, long items
    (one per ray) use small blocks so that the items spread over all multiprocessors.
    """
    if n <= 0:
        return
    sig = _signature(kernel) if _private.usable() else None
    if sig is not None and len(inputs) != len(sig.kinds):
        raise RuntimeError(f"kernel {kernel.key} takes {len(sig.kinds)} inputs after 'first', got {len(inputs)}")
    cmd = None if sig is None else _command(sig, device, block_dim)
    if cmd is None:
        _public_launch(kernel, n, inputs, device, block_dim)
        return
    if device != "cpu":
        cmd.run(sig, 0, n, inputs, current_stream(device))
        return
    align = max(1, align)
    n_threads = min(cpu_threads(), max(1, n // _MIN_ITEMS_PER_THREAD), -(-n // align))
    if n_threads == 1:
        cmd.run(sig, 0, n, inputs, None)
        return
    bounds = [min(n, -(-(n * k // n_threads) // align) * align) for k in range(n_threads + 1)]
    pool = _cpu_pool(n_threads)  # the module was loaded (compiled) above, not in every worker at once
    futures = [
        pool.submit(lambda lo, hi: _command(sig, device, 1).run(sig, lo, hi - lo, inputs, None), lo, hi)
        for lo, hi in zip(bounds[:-1], bounds[1:])
        if hi > lo
    ]
    for f in futures:
        f.result()
