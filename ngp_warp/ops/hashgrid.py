"""Multiresolution hash-grid encoding (instant-NGP), with tiny-cuda-nn's ``HashGrid`` semantics.

Instead of feeding the MLP sinusoids of the position, every position looks up learned features
on ``L`` grids of growing resolution. Coarse grids fit their table and are indexed densely; fine
grids are folded into a table of ``2^log2_hashmap_size`` entries by a spatial hash (collisions
are resolved by the gradient: the surfaces' cells dominate it). Forward and backward are Warp
kernels (``kernels/hashgrid.py``); the autograd layer is in ``hashgrid_autograd``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import warp as wp

from ngp_warp import _wp
from ngp_warp.ops.hashgrid_autograd import HashGridFunction, aligned, compiled_encode
from ngp_warp.ops.op_registry import register
from ngp_warp._reference import hashgrid as reference
from ngp_warp.kernels import hashgrid as K
from ngp_warp.kernels.hashgrid_native import half_vec_type, vec_type

_MAX_ITEMS = 2**31 - 1  # kernels index the [N, L] output with int32


@dataclass(frozen=True)
class LevelTable:
    """Per-level constants of a hash grid, computed exactly as tiny-cuda-nn does (float32)."""

    scales: tuple[float, ...]  # exp2(l * log2(per_level_scale)) * base - 1 (float32 values)
    resolutions: tuple[int, ...]  # ceil(scale) + 1
    sizes: tuple[int, ...]  # entries in the level: min(next_multiple(res^D, 8), 2^log2T)
    offsets: tuple[int, ...]  # L + 1 entry offsets (tcnn's offset table)
    hashed: tuple[bool, ...]  # True where res^D does not fit the level (index by hash)


def level_table(
    n_input_dims: int, n_levels: int, log2_hashmap_size: int, base_resolution: int, per_level_scale: float
) -> LevelTable:
    """The constants tiny-cuda-nn's grid encoding derives from its hyper-parameters.

    ``scale = exp2f(l * log2f(per_level_scale)) * base_resolution - 1`` in float32 (the product
    and the subtraction rounded once, as nvcc contracts them into an FMA), ``resolution =
    ceil(scale) + 1``, ``params_in_level = min(next_multiple(min(res^D, UINT32_MAX/2), 8),
    2^log2_hashmap_size)``. A level is hashed when tcnn's index loop (``stride *= res`` in
    uint32 while ``stride <= params_in_level``) ends with ``stride > params_in_level``.
    """
    log2_scale = np.log2(np.float32(per_level_scale))
    max_params = 0xFFFFFFFF // 2
    scales, resolutions, sizes, offsets, hashed = [], [], [], [0], []
    for level in range(n_levels):
        e = np.exp2(np.float32(level) * log2_scale, dtype=np.float32)
        scale = np.float32(float(e) * float(base_resolution) - 1.0)
        res = int(math.ceil(float(scale))) + 1
        dense = res**n_input_dims
        size = max_params if dense > 2**31 else dense
        size = min(-(-size // 8) * 8, 1 << log2_hashmap_size)
        stride = 1
        for _ in range(n_input_dims):
            if stride > size:
                break
            stride = (stride * res) & 0xFFFFFFFF
        scales.append(float(scale))
        resolutions.append(res)
        sizes.append(size)
        offsets.append(offsets[-1] + size)
        hashed.append(size < stride)
    return LevelTable(tuple(scales), tuple(resolutions), tuple(sizes), tuple(offsets), tuple(hashed))


def _scale_for(desired_resolution: float, base_resolution: int, n_levels: int, per_level_scale: float) -> float:
    """The ``per_level_scale`` whose finest level has ``desired_resolution``."""
    if per_level_scale != 2.0:
        raise ValueError("give either per_level_scale or desired_resolution, not both")
    if not desired_resolution >= 1:
        raise ValueError(f"desired_resolution must be >= 1, got {desired_resolution!r}")
    if n_levels == 1:
        return 1.0
    return math.exp((math.log(desired_resolution) - math.log(base_resolution)) / (n_levels - 1))


class HashGridEncoding(torch.nn.Module):
    """Multiresolution hash-grid encoding of points in ``[0, 1]^D``, as tiny-cuda-nn's ``HashGrid``.

    Encodes ``x`` ``[N, D]`` float32 into ``[N, L*F]`` float32, level-major (level ``l``'s
    ``F`` features at columns ``l*F ... l*F + F - 1``). Level constants, index computation and
    parameter layout are tiny-cuda-nn's, so a tcnn ``HashGrid``'s ``params`` can be loaded here
    (``load_state_dict``) and the other way round:

    * level ``l`` has ``scale = exp2(l*log2(per_level_scale))*base_resolution - 1``, grid
      resolution ``ceil(scale) + 1`` and ``min(next_multiple(res^D, 8), 2^log2_hashmap_size)``
      entries; ``params`` holds the levels one after the other, ``F`` floats per entry;
    * a point sits at ``pos = scale*x + 0.5`` (one fused multiply-add), in the cell
      ``floor(pos)``, with d-linear weights of ``pos - floor(pos)`` (or their smoothstep);
    * a corner's entry is ``x + y*res + z*res^2`` where the level's dense grid fits its
      table, else ``(x*1 ^ y*2654435761 ^ z*805459861) mod entries`` in uint32 arithmetic.
      "Fits" is decided as tcnn does, by a uint32 loop ``stride *= res`` that wraps: levels
      whose ``res^2`` reaches ``2^32`` while ``res <= entries`` (resolutions 2^16 ... 2^19 of the
      default configuration, with ``per_level_scale=2``) are indexed ``(x + y*res) mod
      entries``, z ignored, exactly like tcnn.

    The scales are computed on the host with numpy's float32 ``exp2``/``log2``; tcnn's device
    ``exp2f`` may differ in the last bit where ``l * log2(per_level_scale)`` is not an integer.

    Inputs outside ``[0, 1]`` are *not* clamped, as in tcnn: their cell coordinates wrap
    around in uint32 and land on some (hashed or folded) entry; map your scene into the unit
    cube first.

    Args:
        n_input_dims: D, 2 or 3.
        n_levels: L.
        n_features_per_level: F, 1, 2, 4 or 8.
        log2_hashmap_size: log2 of the largest number of entries per level (1 ... 30).
        base_resolution: the coarsest grid's resolution parameter.
        per_level_scale: growth factor of the scale from one level to the next.
        interpolation: ``"linear"`` or ``"smoothstep"`` (weights ``w^2 (3 - 2w)``, whose
            derivative vanishes on cell faces; handy for second-order smoothness).
        desired_resolution: if given, the finest level's resolution: ``per_level_scale`` becomes
            ``exp((ln(desired_resolution) - ln(base_resolution)) / (L - 1))`` (and must be left
            at its default).
        grad_dtype: ``torch.float32`` (default, exact up to the order of float additions) or
            ``torch.float16``: the table gradient of the hashed levels is accumulated in half
            precision (packed half2 reductions into a scratch buffer) and converted to float32
            at the end. Lossy: each entry's sum is rounded to 11 significant bits at every
            addition; the dense coarse levels, whose entries collect many more additions, stay
            in float32. On sm_90 it is no faster than the float32 path (whose vector reductions
            already cost one operation per corner); before sm_90 it halves the reductions.
        device: where ``params`` lives initially (``.to()`` moves it as usual).

    Attributes:
        params: the flat ``[n_params]`` float32 table, initialised ``U(-1e-4, 1e-4)``.
        n_params, n_output_dims (``L*F``), n_input_dims, n_levels, n_features_per_level,
        log2_hashmap_size, base_resolution, per_level_scale, interpolation, grad_dtype.
        scales, resolutions, offsets (``L + 1`` entry offsets, tcnn's offset table), sizes
        (entries per level), hashed (per-level bool): see :func:`level_table`.

    The forward and backward run on the device of ``x`` (which must be that of ``params``), on
    torch's current stream, without host synchronisation; the backward computes the input
    gradient (``[N, D]``, e.g. for pose refinement or SDF normals) and the table gradient, each
    only when autograd needs it. The backward itself is not differentiable (no second order).

    CUDA scheduling (see ``kernels/hashgrid.py``) is tunable through the attributes
    ``cuda_level_lanes`` (K: consecutive lanes sharing a point, one level each; default
    ``8 // F``, so that they write whole 32-byte sectors), ``cuda_levels_per_thread`` (G:
    levels each of them handles in turn, default 1), ``cuda_paired`` (x-pair merged reductions
    of the table gradient for ``F <= 2``) and ``cuda_dx_levels_per_thread`` (levels per
    input-gradient item; 0: all levels in one item, no atomics).
    """

    def __init__(
        self,
        n_input_dims: int = 3,
        n_levels: int = 16,
        n_features_per_level: int = 2,
        log2_hashmap_size: int = 19,
        base_resolution: int = 16,
        per_level_scale: float = 2.0,
        interpolation: str = "linear",
        *,
        desired_resolution: float | None = None,
        grad_dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
    ):
        super().__init__()
        if n_input_dims not in (2, 3):
            raise ValueError(f"n_input_dims must be 2 or 3, got {n_input_dims}")
        if n_features_per_level not in (1, 2, 4, 8):
            raise ValueError(f"n_features_per_level must be 1, 2, 4 or 8, got {n_features_per_level}")
        if not (isinstance(n_levels, int) and n_levels >= 1):
            raise ValueError(f"n_levels must be a positive int, got {n_levels!r}")
        if not (isinstance(log2_hashmap_size, int) and 1 <= log2_hashmap_size <= 30):
            raise ValueError(f"log2_hashmap_size must be an int in [1, 30], got {log2_hashmap_size!r}")
        if not base_resolution >= 1:
            raise ValueError(f"base_resolution must be >= 1, got {base_resolution!r}")
        interpolation = str(interpolation).lower()
        if interpolation not in K.INTERPOLATIONS:
            raise ValueError(f"interpolation must be one of {K.INTERPOLATIONS}, got {interpolation!r}")
        if desired_resolution is not None:
            per_level_scale = _scale_for(desired_resolution, base_resolution, n_levels, per_level_scale)
        if not per_level_scale > 0:
            raise ValueError(f"per_level_scale must be > 0, got {per_level_scale!r}")
        if grad_dtype not in (torch.float32, torch.float16):
            raise ValueError(f"grad_dtype must be torch.float32 or torch.float16, got {grad_dtype}")

        self.n_input_dims = n_input_dims
        self.n_levels = n_levels
        self.n_features_per_level = n_features_per_level
        self.log2_hashmap_size = log2_hashmap_size
        self.base_resolution = base_resolution
        self.per_level_scale = float(per_level_scale)
        self.interpolation = interpolation
        self.grad_dtype = grad_dtype
        self.n_output_dims = n_levels * n_features_per_level

        table = level_table(n_input_dims, n_levels, log2_hashmap_size, base_resolution, self.per_level_scale)
        if table.offsets[-1] * n_features_per_level > _MAX_ITEMS:
            raise ValueError("the encoding's table would exceed 2^31 floats; lower log2_hashmap_size or n_levels")
        if any(hashed and size & (size - 1) for size, hashed in zip(table.sizes, table.hashed)):
            raise ValueError("hashed levels must have 2^log2_hashmap_size entries")
        self.scales = table.scales
        self.resolutions = table.resolutions
        self.sizes = table.sizes
        self.offsets = table.offsets
        self.hashed = table.hashed
        self.n_params = table.offsets[-1] * n_features_per_level
        # first level accumulated in float16 when grad_dtype is float16: hashed levels only
        self._half_from = next((i for i, h in enumerate(table.hashed) if h), n_levels)

        self.cuda_levels_per_thread = 1
        self.cuda_level_lanes = max(1, min(n_levels, 8 // n_features_per_level))
        self.cuda_paired = n_features_per_level <= 2
        self.cuda_dx_levels_per_thread = max(1, min(n_levels, 8 // n_features_per_level))
        self._cuda_schedule_on_cpu = False  # tests: run the CUDA scheduling code paths on the CPU

        self.params = torch.nn.Parameter(
            torch.empty(self.n_params, dtype=torch.float32, device=device).uniform_(-1e-4, 1e-4)
        )
        meta = [[r, o, s, int(h)] for r, o, s, h in zip(table.resolutions, table.offsets, table.sizes, table.hashed)]
        scales = torch.tensor(table.scales, dtype=torch.float32, device=device)
        self.register_buffer("_scales", scales, persistent=False)
        self.register_buffer("_meta", torch.tensor(meta, dtype=torch.int32, device=device), persistent=False)
        self._wp_meta: dict = {}
        register(self)

    def __getstate__(self):
        # the cached Warp views hold raw pointers: rebuilt on demand after copy / pickle
        return {**super().__getstate__(), "_wp_meta": {}}

    def __setstate__(self, state):
        super().__setstate__(state)
        register(self)

    @classmethod
    def from_finest_resolution(
        cls, finest_resolution: float, n_levels: int = 16, base_resolution: int = 16, **kwargs
    ) -> HashGridEncoding:
        """Encoding whose finest level has ``finest_resolution`` (sets ``per_level_scale``)."""
        return cls(n_levels=n_levels, base_resolution=base_resolution, desired_resolution=finest_resolution, **kwargs)

    def extra_repr(self) -> str:
        return (
            f"n_input_dims={self.n_input_dims}, n_levels={self.n_levels}, "
            f"n_features_per_level={self.n_features_per_level}, log2_hashmap_size={self.log2_hashmap_size}, "
            f"base_resolution={self.base_resolution}, per_level_scale={self.per_level_scale:.6g}, "
            f"interpolation={self.interpolation!r}, n_params={self.n_params}"
        )

    # -- forward ---------------------------------------------------------------------------

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Encode ``x`` ``[..., D]`` float32 (any strides, on the device of ``params``) into
        ``[..., L*F]`` float32, differentiable once in ``x`` and ``params`` (a second derivative
        raises a one-line RuntimeError). float64 points with float64 params (after
        ``.double()``) go through the pure-torch float64 twin
        (:mod:`ngp_warp._reference.hashgrid`), differentiable to any order (``gradcheck``)."""
        flat = self._check_points(x)
        if self.params.dtype == torch.float64:
            out = reference.encode_like(self, flat, exact=True)
        elif torch.compiler.is_compiling():  # the torch.library op: no graph break
            out = compiled_encode(self, flat.contiguous(), self.params)
        else:
            out = HashGridFunction.apply(flat.contiguous(), self.params, self)
        return out if x.dim() == 2 else out.reshape(*x.shape[:-1], out.shape[-1])

    @torch.no_grad()
    def encode(self, x: torch.Tensor, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """The encoding of ``x`` ``[N, D]`` float32 without autograd, as ``[N, L*F]`` ``dtype``:
        float32, or bfloat16 rounded in the kernel (to nearest, ties to even, as
        ``.to(torch.bfloat16)`` rounds the float32 output; NaNs stay NaN, with any payload).
        bfloat16 writes half the bytes and saves the cast, e.g. for a bf16 MLP's no-gradient
        density pass."""
        if dtype not in (torch.float32, torch.bfloat16):
            raise ValueError(f"dtype must be torch.float32 or torch.bfloat16, got {dtype}")
        flat = self._check_points(x)
        if self.params.dtype == torch.float64:
            return reference.encode_like(self, flat, exact=True).reshape(*x.shape[:-1], -1)
        return self._encode(flat.contiguous(), self.params, dtype).reshape(*x.shape[:-1], -1)

    def _check_points(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` as [N, D] (leading dimensions flattened), or ValueError in one line."""
        if not isinstance(x, torch.Tensor):
            raise ValueError(f"HashGridEncoding expects a torch.Tensor, got {type(x).__name__}")
        if x.dim() < 1 or x.shape[-1] != self.n_input_dims:
            raise ValueError(f"HashGridEncoding expects x of shape [..., {self.n_input_dims}], got {list(x.shape)}")
        if self.params.dtype not in (torch.float32, torch.float64):
            raise ValueError(f"the encoding's params are {self.params.dtype}; the kernels take float32 (and "
                             f"float64 runs the float64 twin): cast the module with .float() or .double()")
        if x.dtype != self.params.dtype:
            raise ValueError(f"HashGridEncoding expects {self.params.dtype} positions like its params, got {x.dtype}")
        if x.device != self.params.device:
            raise ValueError(f"x is on {x.device} but the encoding's params are on {self.params.device}")
        if x.dim() != 2:
            x = x.reshape(-1, self.n_input_dims)
        if x.dtype == torch.float64 or torch.compiler.is_compiling():
            return x
        n = x.shape[0]
        config = self._kernels(_wp.device_of(x)).config  # (CPU or CUDA only)
        dx_items = -(-self.n_levels // max(1, config.dx_levels_per_thread)) * n
        if max(self._n_items(config, n), dx_items) > _MAX_ITEMS:  # kernels index items with int32
            raise ValueError(f"too many points for one call ({n}); split the batch")
        return x

    # -- kernel plumbing -------------------------------------------------------------------

    def _kernels(self, device: str) -> K.Kernels:
        half = self.grad_dtype == torch.float16
        D, F, interp = self.n_input_dims, self.n_features_per_level, self.interpolation
        if device == "cpu" and not self._cuda_schedule_on_cpu:
            return K.get_kernels(K.KernelConfig(D, F, interp, 1, 1, False, half, 0))
        G, lanes, paired = int(self.cuda_levels_per_thread), int(self.cuda_level_lanes), bool(self.cuda_paired)
        dx_levels = 0 if device == "cpu" else int(self.cuda_dx_levels_per_thread)  # the CPU has no atomics
        return K.get_kernels(K.KernelConfig(D, F, interp, G, lanes, paired, half, dx_levels))

    def _level_arrays(self):
        """Warp views of the per-level constants (cached per buffer address)."""
        key = (self._scales.data_ptr(), self._meta.data_ptr())
        arrays = self._wp_meta.get(key)
        if arrays is None:
            arrays = (_wp.to_wp(self._scales), _wp.to_wp(self._meta, dtype=wp.vec4i))
            self._wp_meta = {key: arrays}
        return arrays

    def _entries(self, t: torch.Tensor, dtype=None):
        """Warp view of a flat table-shaped tensor as F-vectors."""
        F = self.n_features_per_level
        if F == 1:
            return _wp.to_wp(t.reshape(-1))
        vec = dtype if dtype is not None else vec_type(F)
        return _wp.to_wp(t.reshape(-1, F), dtype=vec)

    def _n_items(self, config: K.KernelConfig, n: int) -> int:
        group = config.levels_per_thread * config.level_lanes
        return -(-self.n_levels // group) * config.level_lanes * n

    def _encode(self, x: torch.Tensor, params: torch.Tensor, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        n, L, F = x.shape[0], self.n_levels, self.n_features_per_level
        out = torch.empty((n, L * F), dtype=dtype, device=x.device)
        if n == 0:
            return out
        device = _wp.device_of(x)
        k = self._kernels(device)
        scales, meta = self._level_arrays()
        if dtype == torch.bfloat16:
            kernel, target = k.forward_bf16, _wp.to_wp(out.view(torch.int16).reshape(-1))
        else:
            kernel, target = k.forward, self._entries(out)
        _wp.launch(
            kernel,
            self._n_items(k.config, n),
            [n, L, _wp.to_wp(x.reshape(-1)), self._entries(aligned(params.detach())), scales, meta, target],
            device,
        )
        return out

    def _grad_params(self, x: torch.Tensor, grad_out: torch.Tensor) -> torch.Tensor:
        n, L, F = x.shape[0], self.n_levels, self.n_features_per_level
        grad = torch.zeros(self.n_params, dtype=torch.float32, device=x.device)
        if n == 0:
            return grad
        device = _wp.device_of(x)
        k = self._kernels(device)
        scales, meta = self._level_arrays()
        half = None
        half_from, half_base = L, self.offsets[-1]
        if k.config.half_grad and self._half_from < L:
            half_from, half_base = self._half_from, self.offsets[self._half_from]
            half = torch.zeros((self.offsets[-1] - half_base) * F, dtype=torch.float16, device=x.device)
        _wp.launch(
            k.backward_params,
            self._n_items(k.config, n),
            [n, L, _wp.to_wp(x.reshape(-1)), scales, meta, self._entries(grad_out), self._entries(grad),
             None if half is None else self._entries(half, half_vec_type(F)), half_from, half_base],
            device,
            align=k.config.level_lanes * n,  # a level group's items (disjoint table regions)
        )
        if half is not None:
            grad[half_base * F :].copy_(half)
        return grad

    def _grad_x(self, x: torch.Tensor, params: torch.Tensor, grad_out: torch.Tensor) -> torch.Tensor:
        n, L, D = x.shape[0], self.n_levels, self.n_input_dims
        device = _wp.device_of(x)
        k = self._kernels(device)
        GX = k.config.dx_levels_per_thread
        grad_x = (torch.empty if GX == 0 else torch.zeros)((n, D), dtype=torch.float32, device=x.device)
        if n == 0:
            return grad_x
        scales, meta = self._level_arrays()
        _wp.launch(
            k.backward_x,
            n if GX == 0 else -(-L // GX) * n,
            [n, L, _wp.to_wp(x.reshape(-1)), self._entries(aligned(params.detach())), scales, meta,
             self._entries(grad_out), _wp.to_wp(grad_x.reshape(-1))],
            device,
        )
        return grad_x
