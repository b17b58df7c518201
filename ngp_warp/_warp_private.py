"""Everything ngp-warp takes from Warp's undocumented internals, in one place (tested: warp-lang 1.19.0).

:func:`ngp_warp._wp.launch` replays a ``wp.Launch`` recorded once per kernel, device, block size
and thread, writing the new arguments into it in place: a few microseconds of Python per launch
where ``wp.launch`` costs tens. That relies on Warp internals:

* ``Kernel.adj.args`` (each ``.label`` and ``.type``) and ``Kernel.is_generic``: a kernel's
  parameters;
* ``Kernel.module.load(device, block_dim)``: the loaded module (a new object after a rebuild);
* ``wp.Launch(kernel, device, block_dim=...)`` built directly, and its ``params`` (the packed
  arguments, launch bounds first: what CPU launches read) and ``params_addr`` (their addresses:
  what CUDA launches pass) lists, written in place;
* the array descriptor (``warp._src.types.array_t``, what ``wp.from_torch(...,
  return_ctype=True)`` returns): built as ``(data, grad, ndim, shape, strides)``, its ``data``
  and ``shape`` fields rewritten in place; ``__ctype__()`` of array annotations and struct
  instances;
* a vector type's ``_wp_scalar_type_``.

:func:`problems` lists what differs on the installed Warp: the types and the kernel
introspection are checked at import, each recorded launch's ``params`` / ``params_addr`` when
it is built. Anything found switches :func:`ngp_warp._wp.launch` to the public ``wp.launch``
(same results, slower) with a one-time warning that names it; ``tests/test_wp.py`` fails on it.
"""

from __future__ import annotations

import ctypes
import warnings
from typing import NamedTuple

import torch
import warp as wp

TESTED_WARP = "1.19.0"

# Warp's array descriptor, a ctypes struct (the type of wp.from_torch(..., return_ctype=True)).
Descriptor = type(wp.array(dtype=wp.float32).__ctype__())

# Warp scalar type -> the torch dtype whose storage it views (as wp.from_torch allows).
_TORCH_SCALAR = {
    wp.float16: torch.float16, wp.float32: torch.float32, wp.float64: torch.float64,
    wp.int8: torch.int8, wp.uint8: torch.uint8, wp.int16: torch.int16, wp.uint16: torch.int16,
    wp.int32: torch.int32, wp.uint32: torch.int32, wp.int64: torch.int64, wp.uint64: torch.int64,
}


class View(NamedTuple):
    """How a tensor becomes a 1-D Warp array of ``dtype`` without ``wp.from_torch``: when it is
    contiguous, of dtype ``scalar`` and shaped ``[N]`` (``width`` 0) or ``[N, width]`` (vectors)."""

    dtype: type
    scalar: torch.dtype | None
    width: int
    size: int  # bytes per element


_views: dict = {}


def view(dtype) -> View:
    """The (cached) :class:`View` of a Warp dtype: scalars and vectors have one, other types a
    ``scalar`` of None (never fits)."""
    v = _views.get(dtype)
    if v is None:
        width = wp.types.type_size(dtype) if wp.types.type_is_vector(dtype) else 0
        simple = width or wp.types.type_is_scalar(dtype)
        scalar = _TORCH_SCALAR.get(getattr(dtype, "_wp_scalar_type_", dtype)) if simple else None
        v = _views[dtype] = View(dtype, scalar, width, wp.types.type_size_in_bytes(dtype))
    return v


def fits(t: torch.Tensor, v: View) -> bool:
    """True when ``t`` can be viewed as a 1-D array of ``v.dtype`` by :func:`descriptor`."""
    if v.width:
        return t.dtype is v.scalar and t.dim() == 2 and t.shape[1] == v.width and t.is_contiguous()
    return t.dtype is v.scalar and t.dim() == 1 and t.is_contiguous()


def descriptor(t: torch.Tensor, v: View) -> Descriptor:
    """Descriptor of the 1-D array ``t`` (which :func:`fits` ``v``), keeping ``t`` alive."""
    a = Descriptor(t.data_ptr(), 0, 1, (t.shape[0],), (v.size,))
    a._ref = t
    return a


# Parameter types whose ctypes value a Python int / float sets directly.
_PLAIN_SCALARS = {wp.int8, wp.uint8, wp.int16, wp.uint16, wp.int32, wp.uint32, wp.int64, wp.uint64,
                  wp.float32, wp.float64}
ARRAY, SCALAR, STRUCT, OTHER = 0, 1, 2, 3


class Signature:
    """Per kernel: the kind of each parameter after ``first`` and, for arrays, the tensor view
    (None for arrays of more than one dimension, which go through ``wp.from_torch``)."""

    __slots__ = ("kernel", "kinds", "views", "nulls", "dtypes")

    def __init__(self, kernel):
        if kernel.is_generic:
            raise TypeError(f"kernel {kernel.key} has generic parameters; launch() needs concrete types")
        self.kernel = kernel
        args = kernel.adj.args[1:]
        self.kinds = [ARRAY if wp.types.is_array(a.type) else SCALAR if a.type in _PLAIN_SCALARS
                      else STRUCT if wp.types.type_is_struct(a.type) else OTHER for a in args]
        self.views = [view(a.type.dtype) if k == ARRAY and a.type.ndim == 1 else None
                      for a, k in zip(args, self.kinds)]
        self.nulls = [a.type.__ctype__() if k == ARRAY else None for a, k in zip(args, self.kinds)]
        self.dtypes = [a.type.dtype if k == ARRAY else None for a, k in zip(args, self.kinds)]

    def descriptor(self, i: int, v) -> Descriptor:
        """Descriptor of input ``i`` for an array parameter off the fast path."""
        if v is None:
            return self.nulls[i]
        if isinstance(v, torch.Tensor):
            return wp.from_torch(v, dtype=self.dtypes[i], requires_grad=False, return_ctype=True)
        if isinstance(v, wp.array):
            return v.__ctype__()
        return v  # already a descriptor


class Command:
    """A reusable ``wp.Launch`` of one kernel on one device, used by one thread.

    Replaying a recorded launch skips ``wp.launch``'s per-call argument checks and packing.
    Each 1-D array parameter has a descriptor owned by the command whose pointer and length are
    overwritten in place for a fitting tensor (see :func:`fits`), so a call costs a few
    attribute writes per argument.
    """

    __slots__ = ("launch", "module_exec", "n", "params", "addresses", "slots")

    def __init__(self, sig: Signature, device: wp.Device, block_dim: int, module_exec):
        self.launch = wp.Launch(sig.kernel, device, block_dim=block_dim)
        self.module_exec = module_exec
        self.n = -1
        self.params = self.launch.params  # [bounds, first, *inputs]
        self.addresses = self.launch.params_addr  # their addresses, for CUDA launches
        self.slots = [None if v is None else Descriptor(0, 0, 1, (0,), (v.size,)) for v in sig.views]

    def _set(self, i: int, desc) -> None:
        self.params[i] = desc
        self.addresses[i] = ctypes.addressof(desc)

    def run(self, sig: Signature, first: int, n: int, inputs: list, stream) -> None:
        params = self.params
        params[1].value = first
        i = 2
        for v, slot, v_view, kind, null in zip(inputs, self.slots, sig.views, sig.kinds, sig.nulls):
            if slot is not None:  # a 1-D array
                if isinstance(v, torch.Tensor) and fits(v, v_view):
                    slot.data = v.data_ptr()
                    slot.shape[0] = v.shape[0]
                    if params[i] is not slot:
                        self._set(i, slot)
                elif v is None:
                    if params[i] is not null:
                        self._set(i, null)
                else:
                    self._set(i, sig.descriptor(i - 2, v))
            elif kind == SCALAR:
                params[i].value = v
            elif kind == STRUCT:  # a struct instance keeps its ctypes value up to date
                desc = v.__ctype__()
                if params[i] is not desc:
                    self._set(i, desc)
            elif kind == ARRAY:
                self._set(i, sig.descriptor(i - 2, v))
            else:
                self.launch.set_param_at_index(i - 1, v)
            i += 1
        if n != self.n:
            self.launch.set_dim(n)
            self.n = n
        self.launch.launch(stream)


def module_exec(kernel, device: wp.Device, block_dim: int):
    """The loaded (compiled) module of ``kernel`` on ``device``; a new object after a rebuild."""
    return kernel.module.load(device, block_dim)


# -- checks ------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def _probe(first: int, values: wp.array(dtype=wp.vec2), scale: float):
    values[first + wp.tid()] = values[first + wp.tid()] * scale


def _static_problems() -> list[str]:
    """What differs from the Warp internals listed in the module docstring, found without
    compiling anything (the descriptor, vector types, kernel introspection)."""
    found = []
    names = [f[0] for f in getattr(Descriptor, "_fields_", ())]
    if names[:2] != ["data", "grad"] or "shape" not in names or "strides" not in names:
        found.append(f"array descriptor fields are {names}, expected data, grad, shape, strides ...")
    else:
        d = Descriptor(1234, 0, 1, (7,), (8,))
        if (d.data, d.shape[0], d.strides[0], d.ndim) != (1234, 7, 8, 1):
            found.append("array descriptor constructor is no longer (data, grad, ndim, shape, strides)")
    if getattr(wp.vec2, "_wp_scalar_type_", None) is not wp.float32:
        found.append("vector types lost _wp_scalar_type_")
    args = getattr(getattr(_probe, "adj", None), "args", None)
    if args is None:
        found.append("Kernel.adj.args is gone")
    elif [a.label for a in args] != ["first", "values", "scale"]:
        found.append(f"Kernel.adj.args labels are {[a.label for a in args]}, expected first, values, scale")
    elif not (wp.types.is_array(args[1].type) and args[1].type.dtype is wp.vec2 and args[1].type.ndim == 1
              and args[2].type is wp.float32 and isinstance(args[1].type.__ctype__(), Descriptor)):
        found.append("Kernel.adj.args types are no longer the annotated Warp types")
    if not isinstance(getattr(_probe, "is_generic", None), bool):
        found.append("Kernel.is_generic is gone")
    if not callable(getattr(getattr(_probe, "module", None), "load", None)):
        found.append("Kernel.module.load is gone")
    return found


def launch_problems(command: Command) -> list[str]:
    """What differs in a freshly built :class:`Command`'s ``wp.Launch``: ``params`` must hold the
    bounds then one packed value per kernel parameter, ``params_addr`` their addresses."""
    launch = command.launch
    params, addresses = getattr(launch, "params", None), getattr(launch, "params_addr", None)
    n_args = len(launch.kernel.adj.args)
    if not isinstance(params, list) or len(params) != 1 + n_args:
        return [f"wp.Launch.params is not a list of the bounds and {n_args} arguments"]
    if addresses is None or len(addresses) != len(params):
        return ["wp.Launch.params_addr is not a ctypes array beside params"]
    if any(addresses[i] != ctypes.addressof(p) for i, p in enumerate(params)):
        return ["wp.Launch.params_addr no longer holds the addresses of params"]
    if not hasattr(params[1], "value"):
        return ["wp.Launch.params no longer holds ctypes scalars"]
    return []


_found: list[str] = _static_problems()
_warned = False


def problems() -> list[str]:
    """Everything found so far that differs from the Warp internals this module relies on."""
    return list(_found)


def usable() -> bool:
    """True while no problem has been found: recorded launches may be replayed."""
    return not _found


def report(found: list[str]) -> None:
    """Record ``found`` problems; the first time, warn that launches take the public path."""
    global _warned
    _found.extend(p for p in found if p not in _found)
    if _found and not _warned:
        _warned = True
        warnings.warn(
            f"ngp_warp: warp-lang {wp.__version__} differs from the Warp internals ngp_warp was tested with "
            f"({TESTED_WARP}): {'; '.join(_found)}. Kernels are launched through wp.launch instead (slower).",
            RuntimeWarning,
            stacklevel=3,
        )


report([])  # warns at import when the static checks found anything
