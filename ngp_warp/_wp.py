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
millisecond on a GPU. There are no per-call dtype or length checks: the public functions
validate their inputs first.
"""

from __future__ import annotations

import ctypes
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import torch
import warp as wp

# Warp's array descriptor (what ``wp.from_torch(..., return_ctype=True)`` returns), a ctypes struct.
_Descriptor = type(wp.array(dtype=wp.float32).__ctype__())

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


# Warp scalar type -> the torch dtype whose storage it views (as wp.from_torch allows).
_TORCH_SCALAR = {
    wp.float16: torch.float16, wp.float32: torch.float32, wp.float64: torch.float64,
    wp.int8: torch.int8, wp.uint8: torch.uint8, wp.int16: torch.int16, wp.uint16: torch.int16,
    wp.int32: torch.int32, wp.uint32: torch.int32, wp.int64: torch.int64, wp.uint64: torch.int64,
}


class _View(NamedTuple):
    """How a tensor becomes a 1-D Warp array of ``dtype`` without ``wp.from_torch``: when it is
    contiguous, of dtype ``scalar`` and shaped ``[N]`` (``width`` 0) or ``[N, width]`` (vectors)."""

    dtype: type
    scalar: torch.dtype | None
    width: int
    size: int  # bytes per element


_views: dict = {}


def _view(dtype) -> _View:
    v = _views.get(dtype)
    if v is None:
        shape = tuple(getattr(dtype, "_shape_", ()))
        scalar = _TORCH_SCALAR.get(getattr(dtype, "_wp_scalar_type_", dtype)) if len(shape) <= 1 else None
        v = _views[dtype] = _View(dtype, scalar, shape[0] if shape else 0, wp.types.type_size_in_bytes(dtype))
    return v


def _fits(t: torch.Tensor, view: _View) -> bool:
    if view.width:
        return t.dtype is view.scalar and t.dim() == 2 and t.shape[1] == view.width and t.is_contiguous()
    return t.dtype is view.scalar and t.dim() == 1 and t.is_contiguous()


def to_wp(t: torch.Tensor, dtype=None) -> _Descriptor:
    """Zero-copy Warp view of a tensor (no gradient buffer), as an array descriptor that keeps
    ``t`` alive; :func:`launch` and ``wp.launch`` take it for an array parameter.

    ``dtype`` defaults to the tensor's scalar type; a vector dtype (``wp.vec3`` ...) consumes
    the trailing dimension. Mismatched dtypes or inner shapes raise ``RuntimeError``.
    """
    view = None if dtype is None else _view(dtype)
    if view is None or not _fits(t, view):
        return wp.from_torch(t, dtype=dtype, requires_grad=False, return_ctype=True)
    a = _Descriptor(t.data_ptr(), 0, 1, (t.shape[0],), (view.size,))
    a._ref = t
    return a


def cpu_threads() -> int:
    """Threads used for CPU launches (``NGP_WARP_CPU_THREADS`` overrides the core count)."""
    env = os.environ.get("NGP_WARP_CPU_THREADS")
    if env:
        if not env.strip().isdigit():
            raise ValueError(f"NGP_WARP_CPU_THREADS must be a positive integer, got {env!r}")
        return max(1, int(env))
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)


_pool: ThreadPoolExecutor | None = None
_MIN_ITEMS_PER_THREAD = 2048


def _cpu_pool(n: int) -> ThreadPoolExecutor:
    global _pool
    if _pool is None or _pool._max_workers < n:
        _pool = ThreadPoolExecutor(max_workers=n, thread_name_prefix="ngp-warp-cpu")
    return _pool


# Parameter types whose ctypes value a Python int / float sets directly.
_PLAIN_SCALARS = {wp.int8, wp.uint8, wp.int16, wp.uint16, wp.int32, wp.uint32, wp.int64, wp.uint64,
                  wp.float32, wp.float64}
_ARRAY, _SCALAR, _STRUCT, _OTHER = 0, 1, 2, 3


class _Signature:
    """Per kernel: the kind of each parameter after ``first`` and, for arrays, the tensor view
    (None for arrays of more than one dimension, which go through ``wp.from_torch``)."""

    __slots__ = ("kernel", "kinds", "views", "nulls")

    def __init__(self, kernel):
        if kernel.is_generic:
            raise TypeError(f"kernel {kernel.key} has generic parameters; launch() needs concrete types")
        self.kernel = kernel
        args = kernel.adj.args[1:]
        self.kinds = [_ARRAY if wp.types.is_array(a.type) else _SCALAR if a.type in _PLAIN_SCALARS
                      else _STRUCT if wp.types.type_is_struct(a.type) else _OTHER for a in args]
        self.views = [_view(a.type.dtype) if k == _ARRAY and a.type.ndim == 1 else None
                      for a, k in zip(args, self.kinds)]
        self.nulls = [a.type.__ctype__() if k == _ARRAY else None for a, k in zip(args, self.kinds)]

    def descriptor(self, i: int, v) -> _Descriptor:
        """Descriptor of input ``i`` for an array parameter off the fast path."""
        if v is None:
            return self.nulls[i]
        if isinstance(v, torch.Tensor):
            dtype = self.kernel.adj.args[i + 1].type.dtype
            return wp.from_torch(v, dtype=dtype, requires_grad=False, return_ctype=True)
        if isinstance(v, wp.array):
            return v.__ctype__()
        return v  # already a descriptor


class _Command:
    """A reusable ``wp.Launch`` of one kernel on one device, used by one thread.

    Replaying a recorded launch skips ``wp.launch``'s per-call argument checks and packing.
    Each 1-D array parameter has a descriptor owned by the command whose pointer and length are
    overwritten in place for a fitting tensor (see :func:`_fits`), so a call costs a few
    attribute writes per argument.
    """

    __slots__ = ("launch", "module_exec", "n", "params", "addresses", "slots")

    def __init__(self, sig: _Signature, device: wp.Device, block_dim: int, module_exec):
        self.launch = wp.Launch(sig.kernel, device, block_dim=block_dim)
        self.module_exec = module_exec
        self.n = -1
        self.params = self.launch.params  # [bounds, first, *inputs]
        self.addresses = self.launch.params_addr  # their addresses, for CUDA launches
        self.slots = [None if v is None else _Descriptor(0, 0, 1, (0,), (v.size,)) for v in sig.views]

    def _set(self, i: int, desc) -> None:
        self.params[i] = desc
        self.addresses[i] = ctypes.addressof(desc)

    def run(self, sig: _Signature, first: int, n: int, inputs: list, stream) -> None:
        params = self.params
        params[1].value = first
        i = 2
        for v, slot, view, kind, null in zip(inputs, self.slots, sig.views, sig.kinds, sig.nulls):
            if slot is not None:  # a 1-D array
                if isinstance(v, torch.Tensor) and _fits(v, view):
                    slot.data = v.data_ptr()
                    slot.shape[0] = v.shape[0]
                    if params[i] is not slot:
                        self._set(i, slot)
                elif v is None:
                    if params[i] is not null:
                        self._set(i, null)
                else:
                    self._set(i, sig.descriptor(i - 2, v))
            elif kind == _SCALAR:
                params[i].value = v
            elif kind == _STRUCT:  # a struct instance keeps its ctypes value up to date
                desc = v.__ctype__()
                if params[i] is not desc:
                    self._set(i, desc)
            elif kind == _ARRAY:
                self._set(i, sig.descriptor(i - 2, v))
            else:
                self.launch.set_param_at_index(i - 1, v)
            i += 1
        if n != self.n:
            self.launch.set_dim(n)
            self.n = n
        self.launch.launch(stream)


_signatures: dict = {}
_local = threading.local()
_devices: dict[str, wp.Device] = {}


def _signature(kernel) -> _Signature:
    sig = _signatures.get(kernel)
    if sig is None:
        sig = _signatures[kernel] = _Signature(kernel)
    return sig


def _command(sig: _Signature, device: str, block_dim: int) -> _Command:
    commands = getattr(_local, "commands", None)
    if commands is None:
        commands = _local.commands = {}
    dev = _devices.get(device)
    if dev is None:
        dev = _devices[device] = wp.get_device(device)
    if dev.is_cpu:
        block_dim = 1  # as wp.launch resolves it on the CPU
    module_exec = sig.kernel.module.load(dev, block_dim)
    cmd = commands.get((sig.kernel, device, block_dim))
    if cmd is None or cmd.module_exec is not module_exec:  # new, or the module was rebuilt
        cmd = commands[(sig.kernel, device, block_dim)] = _Command(sig, dev, block_dim, module_exec)
    return cmd


def launch(kernel, n: int, inputs: list, device: str, align: int = 1, block_dim: int = 256) -> None:
    """Launch ``kernel(first, *inputs)`` over ``n`` items on ``device``.

    ``inputs`` holds, per kernel parameter after ``first``: a tensor (viewed with the
    parameter's Warp dtype, see :func:`to_wp`), a Warp array or array descriptor, None for an
    unused array, a Python scalar, or a Warp struct instance. Each thread replays its own recorded launch of the
    kernel with the new arguments (no per-call ``wp.launch`` argument checks: callers validate).

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
    sig = _signature(kernel)
    if len(inputs) != len(sig.kinds):
        raise RuntimeError(f"kernel {kernel.key} takes {len(sig.kinds)} inputs after 'first', got {len(inputs)}")
    if device != "cpu":
        _command(sig, device, block_dim).run(sig, 0, n, inputs, current_stream(device))
        return
    align = max(1, align)
    n_threads = min(cpu_threads(), max(1, n // _MIN_ITEMS_PER_THREAD), -(-n // align))
    if n_threads == 1:
        _command(sig, device, 1).run(sig, 0, n, inputs, None)
        return
    bounds = [min(n, -(-(n * k // n_threads) // align) * align) for k in range(n_threads + 1)]
    _command(sig, device, 1)  # load (compile) the module here once, not in every worker at once
    pool = _cpu_pool(n_threads)
    futures = [
        pool.submit(lambda lo, hi: _command(sig, device, 1).run(sig, lo, hi - lo, inputs, None), lo, hi)
        for lo, hi in zip(bounds[:-1], bounds[1:])
        if hi > lo
    ]
    for f in futures:
        f.result()
