"""Warp kernels of the multiresolution hash-grid encoding (tiny-cuda-nn ``HashGrid`` semantics).

Each level ``l`` of the encoding is a table of ``F``-feature entries. A point ``x`` in ``[0, 1]^D``
is placed on the level's grid (``pos = scale_l * x + 0.5``, computed with one fused multiply-add
as tiny-cuda-nn does), the ``2^D`` corners of its cell are looked up -- densely indexed
(``x + y*res + z*res^2``) on coarse levels whose grid fits the table, through the XOR hash of
``coord_d * prime_d`` (uint32 arithmetic, primes 1, 2654435761, 805459861) on finer ones -- and
the corner features are blended with d-linear (or smoothstep) weights.

Kernels are specialised per configuration (dimension ``D``, features ``F``, interpolation, and
the scheduling knobs below) by :func:`get_kernels`, which builds and caches one Warp module per
configuration from small factories: the shared Warp functions are in ``hashgrid_funcs.py``, the
native memory snippets in ``hashgrid_native.py``. All kernels take ``first`` (offset of the
launch's first item, see ``ngp_warp._wp.launch``) as their first argument, then:

* ``n``: number of points, ``n_levels``;
* ``x``: the points, flat ``[N*D]`` float32;
* ``scales``: per-level float32 ``scale_l`` and ``meta``: per-level ``vec4i`` holding
  ``(resolution, offset in entries, entries in the level, hashed flag)``.

Items are scheduled level-major, by groups of ``K*G`` consecutive levels (``K =
level_lanes``, ``G = levels_per_thread``): the ``K*n`` items of a group are ordered point by
point, ``K`` consecutive items (lanes of one warp) sharing a point, and the item of lane ``j``
handles levels ``group*K*G + j + K*t`` for ``t < G``, one after the other. So at any moment the
GPU works on the tables of ``K*G`` levels only, and those stay resident in L2, while the lanes
of a point write (forward) or read (backward) ``K*F`` contiguous floats of the row-major
``[N, L*F]`` output per instruction -- a whole 32-byte sector for ``K*F = 8`` -- instead of
scattered ``F``-vectors that the L2 would have to merge with the other levels' parts of the
same sector much later.

The table gradient is added with vector reductions (sm_90), one per corner instead of one per
feature. With ``paired``, the table gradient of the two corners of a cell that differ only in
x is added by one 16-byte reduction whenever they fall into the same aligned pair of table
entries (for hashed levels: whenever the cell's x coordinate is even, since the x prime is 1).
The corner indices are computed without branches, so that the forward issues all 2^D loads of
a level back to back. CPU launches of the table-gradient kernel must give each thread whole
level groups (the additions there are not atomic).
"""

import functools
from typing import NamedTuple

import warp as wp

from ngp_warp.kernels import hashgrid_funcs as funcs
from ngp_warp.kernels.hashgrid_native import half_vec_type, native_io, vec_type

LINEAR = "linear"
SMOOTHSTEP = "smoothstep"
INTERPOLATIONS = (LINEAR, SMOOTHSTEP)


class KernelConfig(NamedTuple):
    """Everything a compiled kernel set depends on."""

    n_dims: int  # D, 2 or 3
    n_features: int  # F, 1, 2, 4 or 8
    interpolation: str  # "linear" or "smoothstep"
    levels_per_thread: int = 1  # G: levels one forward / table-gradient item handles in turn
    level_lanes: int = 1  # K: consecutive items (lanes) that share a point, one level each
    paired: bool = False  # x-pair merged table-gradient reductions (F <= 2 only)
    half_grad: bool = False  # table gradient of hashed levels accumulated in float16
    dx_levels_per_thread: int = 0  # levels per d/dx item; 0: all levels, no atomics


class Kernels(NamedTuple):
    config: KernelConfig
    forward: object
    forward_bf16: object
    backward_params: object
    backward_x: object


@functools.cache
def get_kernels(config: KernelConfig) -> Kernels:
    """Build (once per configuration) the forward, table-gradient and input-gradient kernels.

    Kernel signatures (after ``first``, see the module docstring):

    * ``forward(n, n_levels, x, params: array(V), scales, meta, out: array(V))`` with ``out``
      the row-major ``[N, L*F]`` output seen as ``N*L`` F-vectors. Items: ``ceil(L/(K*G))*K*N``.
      ``forward_bf16`` takes the same arguments but ``out: array(int16)``, the ``N*L*F``
      bfloat16 bits of the output.
    * ``backward_params(n, n_levels, x, scales, meta, grad_out: array(V), grad: array(V),
      grad_half: array(VH), half_from_level, half_base)``: adds ``d out / d params`` into
      ``grad`` (float32, all levels below ``half_from_level``) and ``grad_half`` (float16,
      entries from ``half_base`` on, levels from ``half_from_level`` on, when
      ``config.half_grad``). Items: ``ceil(L/(K*G))*K*N``; items of different level groups
      touch disjoint table regions.
    * ``backward_x(n, n_levels, x, params, scales, meta, grad_out, grad_x)``: ``grad_x`` is the
      flat ``[N*D]`` input gradient; written when ``dx_levels_per_thread == 0`` (items ``N``),
      accumulated atomically into a zeroed buffer otherwise (items ``ceil(L/Gx) * N``).
    """
    _check(config)
    D, F, interp, G, K, paired, half_grad, GX = config
    paired = bool(paired) and F <= 2
    module = f"ngp_warp.ops.hashgrid.D{D}F{F}{interp[0]}G{G}K{K}p{int(paired)}h{int(half_grad)}x{GX}"
    io = native_io(F)
    # (locate, corner_indices, corner_weight) and (join_pair, any_nonzero, dot_f)
    cell = (funcs.locate_func(D, interp == SMOOTHSTEP), *funcs.corner_funcs(D))
    features = funcs.feature_funcs(F)
    encode_level, level_dx = funcs.level_funcs(D, F, *cell, features[2], io.gather)
    schedule = funcs.schedule_func(K)
    forward = _forward_kernel(module, "forward", F, G, K, schedule, encode_level, io.store, vec_type(F))
    forward_bf16 = _forward_kernel(module, "forward_bf16", F, G, K, schedule, encode_level, io.store_bf16, wp.int16)
    backward_params = _backward_params_kernel(module, config._replace(paired=paired), schedule, cell, features, io)
    backward_x = _backward_x_kernel(module, D, F, GX, level_dx, io.load_stream)
    return Kernels(config, forward, forward_bf16, backward_params, backward_x)


def _check(config: KernelConfig) -> None:
    D, F, interp, G, K, _, _, GX = config
    if D not in (2, 3):
        raise ValueError(f"n_dims must be 2 or 3, got {D}")
    if F not in (1, 2, 4, 8):
        raise ValueError(f"n_features must be 1, 2, 4 or 8, got {F}")
    if interp not in INTERPOLATIONS:
        raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, got {interp!r}")
    if G < 1 or K < 1 or GX < 0:
        raise ValueError("levels_per_thread and level_lanes must be >= 1, dx_levels_per_thread >= 0")


def _forward_kernel(module: str, name: str, F: int, G: int, K: int, schedule, encode_level, store, out_dtype):
    """The forward kernel writing each (point, level) entry with ``store`` into ``out`` (of
    ``out_dtype``): float32 F-vectors, or ``store_bf16``'s bfloat16 bits (int16), half the bytes
    written and no cast after."""
    V = vec_type(F)
    KG = K * G  # levels per level group

    # out[p, level] = sum_c weight_c(x_p) * params[offset_level + index_c(x_p)]  (encode_level)
    @wp.kernel(enable_backward=False, module=module, grid_stride=False, name=name)
    def forward(
        first: int,
        n: int,
        n_levels: int,
        x: wp.array(dtype=wp.float32),
        params: wp.array(dtype=V),
        scales: wp.array(dtype=wp.float32),
        meta: wp.array(dtype=wp.vec4i),
        out: wp.array(dtype=out_dtype),
    ):
        grp, p, lane = schedule(first + wp.tid(), n)
        for j in range(G):
            level = grp * KG + j * K + lane
            if level < n_levels:
                store(out, p * n_levels + level, encode_level(x, p, params, scales[level], meta[level]))

    return forward


def _backward_params_kernel(module: str, config: KernelConfig, schedule, cell, features, io):
    """The table-gradient kernel (see :func:`get_kernels`). ``cell``: (locate, corner_indices,
    corner_weight), ``features``: (join_pair, any_nonzero, dot_f) of ``hashgrid_funcs``, ``io``:
    the native helpers of ``F``; ``config.paired`` already resolved (``F <= 2`` only)."""
    D, F, _, G, K, paired, half_grad, _ = config
    locate, corner_indices, corner_weight = cell
    join_pair, any_nonzero, _ = features
    load_stream = io.load_stream
    scatter = funcs.scatter_func(F, vec_type(F), io.red, io.red_half, half_grad)
    scatter_pair = funcs.scatter_func(F, vec_type(2 * F), io.red_pair, io.red_half_pair, half_grad) if paired else None
    V, VH = vec_type(F), half_vec_type(F)
    NC = 1 << D  # corners per cell
    NH = NC // 2  # x-pairs of corners
    KG = K * G

    # grad[offset_level + index_c(x_p)] += weight_c(x_p) * grad_out[p, level], for every corner c
    @wp.kernel(enable_backward=False, module=module, grid_stride=False, name="backward_params")
    def backward_params(
        first: int,
        n: int,
        n_levels: int,
        x: wp.array(dtype=wp.float32),
        scales: wp.array(dtype=wp.float32),
        meta: wp.array(dtype=wp.vec4i),
        grad_out: wp.array(dtype=V),
        grad: wp.array(dtype=V),
        grad_half: wp.array(dtype=VH),
        half_from_level: int,
        half_base: int,
    ):
        grp, p, lane = schedule(first + wp.tid(), n)
        hb = wp.uint32(half_base)
        for j in range(G):
            level = grp * KG + j * K + lane
            if level < n_levels:
                go = load_stream(grad_out, p * n_levels + level)
                if not any_nonzero(go):
                    continue  # e.g. the padding rows of a pruned batch: adding zeros changes nothing
                m = meta[level]
                res = wp.uint32(m[0])
                off = wp.uint32(m[1])
                size = wp.uint32(m[2])
                hashed = m[3]
                use_half = level >= half_from_level
                g, w, dw = locate(x, p, scales[level])
                idx = corner_indices(g, res, size, hashed)
                if wp.static(paired):
                    for ch in range(NH):
                        c = 2 * ch
                        i0 = idx[c]
                        i1 = idx[c + 1]
                        g0 = corner_weight(w, c) * go
                        g1 = corner_weight(w, c + 1) * go
                        if i1 == (i0 ^ wp.uint32(1)):
                            odd = (i0 & wp.uint32(1)) != 0
                            e = off + (i0 & ~wp.uint32(1))
                            scatter_pair(grad, grad_half, use_half, e, hb, join_pair(g0, g1, odd))
                        else:
                            scatter(grad, grad_half, use_half, off + i0, hb, g0)
                            scatter(grad, grad_half, use_half, off + i1, hb, g1)
                else:
                    for c in range(NC):
                        scatter(grad, grad_half, use_half, off + idx[c], hb, corner_weight(w, c) * go)

    return backward_params


def _backward_x_kernel(module: str, D: int, F: int, GX: int, level_dx, load_stream):
    """The input-gradient kernel: one item per point (``GX == 0``) or per (point, ``GX`` levels)."""
    V = vec_type(F)
    VD = wp.types.vector(length=D, dtype=wp.float32)

    # grad_x[p] = sum_level level_dx(x_p, grad_out[p, level])  (written, or added atomically)
    @wp.kernel(enable_backward=False, module=module, grid_stride=False, name="backward_x")
    def backward_x(
        first: int,
        n: int,
        n_levels: int,
        x: wp.array(dtype=wp.float32),
        params: wp.array(dtype=V),
        scales: wp.array(dtype=wp.float32),
        meta: wp.array(dtype=wp.vec4i),
        grad_out: wp.array(dtype=V),
        grad_x: wp.array(dtype=wp.float32),
    ):
        item = first + wp.tid()
        if wp.static(GX == 0):
            p = item
            acc = VD()
            for level in range(n_levels):
                go = load_stream(grad_out, p * n_levels + level)
                acc += level_dx(x, p, params, scales[level], meta[level], go)
            for d in range(D):
                grad_x[p * D + d] = acc[d]
        else:
            grp = item // n
            p = item - grp * n
            acc = VD()
            for j in range(GX):
                level = grp * GX + j
                if level < n_levels:
                    go = load_stream(grad_out, p * n_levels + level)
                    acc += level_dx(x, p, params, scales[level], meta[level], go)
            for d in range(D):
                wp.atomic_add(grad_x, p * D + d, acc[d])

    return backward_x
