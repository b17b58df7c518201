"""Warp kernels of the multiresolution hash-grid encoding (tiny-cuda-nn ``HashGrid`` semantics).

Each level ``l`` of the encoding is a table of ``F``-feature entries. A point ``x`` in ``[0, 1]^D``
is placed on the level's grid (``pos = scale_l * x + 0.5``, computed with one fused multiply-add
as tiny-cuda-nn does), the ``2^D`` corners of its cell are looked up -- densely indexed
(``x + y*res + z*res^2``) on coarse levels whose grid fits the table, through the XOR hash of
``coord_d * prime_d`` (uint32 arithmetic, primes 1, 2654435761, 805459861) on finer ones -- and
the corner features are blended with d-linear (or smoothstep) weights.

Kernels are specialised per configuration (dimension ``D``, features ``F``, interpolation, and
the scheduling knobs below) by :func:`get_kernels`, which builds and caches one Warp module per
configuration. All kernels take ``first`` (offset of the launch's first item, see
``ngp_warp._wp.launch``) as their first argument, then:

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

CUDA-specific memory instructions live in small native snippets: vector loads through the
read-only path, streaming (evict-first) stores and loads for the output and its gradient, so
that they do not push the tables out of L2, and vector reductions (``red.global.v2/v4.f32``,
sm_90) for the table gradient, one per corner instead of one per feature. With ``paired``,
the table gradient of the two corners of a cell that differ only in x is added by one 16-byte
reduction whenever they fall into the same aligned pair of table entries (for hashed levels:
whenever the cell's x coordinate is even, since the x prime is 1). The corner indices are
computed without branches, so that the forward issues all 2^D loads of a level back to back.
On the CPU the snippets fall back to plain C++; CPU launches of the table-gradient kernel must
give each thread whole level groups (the additions there are not atomic).
"""

import functools
from typing import NamedTuple

import warp as wp

PRIMES = (1, 2654435761, 805459861)
LINEAR = "linear"
SMOOTHSTEP = "smoothstep"
INTERPOLATIONS = (LINEAR, SMOOTHSTEP)

_P1 = wp.constant(wp.uint32(PRIMES[1]))
_P2 = wp.constant(wp.uint32(PRIMES[2]))
_ALL_BITS = wp.constant(wp.uint32(0xFFFFFFFF))


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


# ---------------------------------------------------------------------------------------------
# native snippets (generated per F)
# ---------------------------------------------------------------------------------------------


def _vec_ctype(n):
    return "wp::float32" if n == 1 else f"wp::vec_t<{n}, wp::float32>"


def _regs(n, first=0):
    return ", ".join(f"%{first + i}" for i in range(n))


def _load_snippet(n, arr, cache):
    """C++ body returning ``n`` floats read at float offset ``e * n`` of ``arr``."""
    ct = _vec_ctype(n)
    lines = [f"const float* q = reinterpret_cast<const float*>({arr}.data) + (size_t)e * {n};"]
    lines.append("#if defined(__CUDA_ARCH__)")
    lines.append(f"float v[{n}];")
    for k in range(0, n, 4):
        w = min(4, n - k)
        vec = "" if w == 1 else f".v{w}"
        outs = ", ".join(f'"=f"(v[{k + i}])' for i in range(w))
        regs = _regs(w)
        lhs = regs if w == 1 else "{" + regs + "}"
        lines.append(f'asm("ld.global.{cache}{vec}.f32 {lhs}, [%{w}];" : {outs} : "l"(q + {k}));')
    lines.append("#else")
    lines.append("const float* v = q;")
    lines.append("#endif")
    if n == 1:
        lines.append("return v[0];")
    else:
        lines.append(f"{ct} r;")
        lines.append(f"for (int i = 0; i < {n}; ++i) r.c[i] = v[i];")
        lines.append("return r;")
    return "\n".join(lines) + "\n"


def _store_snippet(n):
    """C++ body storing ``v`` (``n`` floats) at float offset ``e * n`` of ``o``, evict-first."""
    lines = [f"float* q = reinterpret_cast<float*>(o.data) + (size_t)e * {n};"]
    vals = ["v"] if n == 1 else [f"v.c[{i}]" for i in range(n)]
    lines.append("#if defined(__CUDA_ARCH__)")
    for k in range(0, n, 4):
        w = min(4, n - k)
        vec = "" if w == 1 else f".v{w}"
        regs = _regs(w, 1)
        rhs = regs if w == 1 else "{" + regs + "}"
        ins = ", ".join(f'"f"({vals[k + i]})' for i in range(w))
        lines.append(f'asm volatile("st.global.cs{vec}.f32 [%0], {rhs};" :: "l"(q + {k}), {ins} : "memory");')
    lines.append("#else")
    for i in range(n):
        lines.append(f"q[{i}] = {vals[i]};")
    lines.append("#endif")
    return "\n".join(lines) + "\n"


def _store_bf16_snippet(n):
    """C++ body storing ``v`` (``n`` floats) rounded to bfloat16 (to nearest, ties to even) at
    bfloat16 offset ``e * n`` of ``o``, evict-first. sm_80 and later: packed ``cvt.rn.bf16x2``
    and one vector store; elsewhere (CPU, older GPUs) the same rounding on the bits."""
    vals = ["v"] if n == 1 else [f"v.c[{i}]" for i in range(n)]
    lines = [f"unsigned short* q = reinterpret_cast<unsigned short*>(o.data) + (size_t)e * {n};"]
    lines.append("#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800")
    pairs = [(vals[2 * i + 1], vals[2 * i]) for i in range(n // 2)] if n > 1 else [("0.0f", vals[0])]
    lines.append(f"unsigned int h[{len(pairs)}];")
    for i, (hi, lo) in enumerate(pairs):  # cvt.rn.bf16x2.f32 d, a, b puts a in the upper half
        lines.append(f'asm("cvt.rn.bf16x2.f32 %0, %1, %2;" : "=r"(h[{i}]) : "f"({hi}), "f"({lo}));')
    if n == 1:
        lines.append('asm volatile("st.global.cs.u16 [%0], %1;" :: "l"(q), "h"((unsigned short)h[0]) : "memory");')
    else:
        w = len(pairs)
        vec = "" if w == 1 else f".v{w}"
        rhs = "%1" if w == 1 else "{" + _regs(w, 1) + "}"
        ins = ", ".join(f'"r"(h[{i}])' for i in range(w))
        lines.append(f'asm volatile("st.global.cs{vec}.u32 [%0], {rhs};" :: "l"(q), {ins} : "memory");')
    lines.append("#else")
    for i in range(n):
        lines.append(f"{{ union {{ float f; unsigned int u; }} c; c.f = {vals[i]};")
        lines.append("  q[%d] = (unsigned short)(c.f != c.f ? 0x7FC0u : (c.u + 0x7FFFu + ((c.u >> 16) & 1u)) >> 16); }" % i)
    lines.append("#endif")
    return "\n".join(lines) + "\n"


def _red_snippet(n, stride=None):
    """C++ body adding ``v`` (``n`` floats) at float offset ``e * stride`` (default ``n``) of ``g``.

    sm_90 and later: vector reductions of up to 4 floats; older GPUs: one atomic per float;
    CPU: plain (non-atomic) additions.
    """
    vals = ["v"] if n == 1 else [f"v.c[{i}]" for i in range(n)]
    lines = [f"float* q = reinterpret_cast<float*>(g.data) + (size_t)e * {stride or n};"]
    lines.append("#if defined(__CUDA_ARCH__)")
    lines.append("#if __CUDA_ARCH__ >= 900")
    for k in range(0, n, 4):
        w = min(4, n - k)
        ins = ", ".join(f'"f"({vals[k + i]})' for i in range(w))
        if w == 1:
            lines.append(f'asm volatile("red.global.add.f32 [%0], %1;" :: "l"(q + {k}), {ins} : "memory");')
        else:
            rhs = "{" + _regs(w, 1) + "}"
            lines.append(f'asm volatile("red.global.v{w}.f32.add [%0], {rhs};" :: "l"(q + {k}), {ins} : "memory");')
    lines.append("#else")
    for i in range(n):
        lines.append(f"atomicAdd(q + {i}, {vals[i]});")
    lines.append("#endif")
    lines.append("#else")
    for i in range(n):
        lines.append(f"q[{i}] += {vals[i]};")
    lines.append("#endif")
    return "\n".join(lines) + "\n"


def _red_half_snippet(n, stride=None):
    """C++ body adding ``v`` (``n`` floats, rounded to half) at half offset ``e * stride`` of ``g``.

    CUDA: packed ``f16x2`` reductions (vectors of up to 4 of them on sm_90).
    """
    vals = ["v"] if n == 1 else [f"v.c[{i}]" for i in range(n)]
    lines = [f"wp::half* q = reinterpret_cast<wp::half*>(g.data) + (size_t)e * {stride or n};"]
    lines.append("#if defined(__CUDA_ARCH__)")
    if n == 1:
        lines.append("unsigned short h;")
        lines.append('asm("cvt.rn.f16.f32 %0, %1;" : "=h"(h) : "f"(v));')
        lines.append('asm volatile("red.global.add.noftz.f16 [%0], %1;" :: "l"(q), "h"(h) : "memory");')
    else:
        n2 = n // 2
        lines.append(f"unsigned int h[{n2}];")
        for i in range(n2):
            # cvt.rn.f16x2.f32 d, a, b puts a in the upper and b in the lower half
            hi, lo = vals[2 * i + 1], vals[2 * i]
            lines.append(f'asm("cvt.rn.f16x2.f32 %0, %1, %2;" : "=r"(h[{i}]) : "f"({hi}), "f"({lo}));')
        lines.append("#if __CUDA_ARCH__ >= 900")
        for k in range(0, n2, 4):
            w = min(4, n2 - k)
            ins = ", ".join(f'"r"(h[{k + i}])' for i in range(w))
            if w == 1:
                lines.append(
                    f'asm volatile("red.global.add.noftz.f16x2 [%0], %1;" :: "l"(q + {2 * k}), {ins} : "memory");'
                )
            else:
                rhs = "{" + _regs(w, 1) + "}"
                red = f"red.global.v{w}.f16x2.add.noftz [%0], {rhs};"
                lines.append(f'asm volatile("{red}" :: "l"(q + {2 * k}), {ins} : "memory");')
        lines.append("#else")
        for i in range(n2):
            lines.append(
                f'asm volatile("red.global.add.noftz.f16x2 [%0], %1;" :: "l"(q + {2 * i}), "r"(h[{i}]) : "memory");'
            )
        lines.append("#endif")
    lines.append("#else")
    for i in range(n):
        lines.append(f"q[{i}] = wp::float_to_half(wp::half_to_float(q[{i}]) + {vals[i]});")
    lines.append("#endif")
    return "\n".join(lines) + "\n"


_FMA_SNIPPET = """
#if defined(__CUDA_ARCH__)
return fmaf(a, b, c);
#else
return __builtin_fmaf(a, b, c);
#endif
"""


@wp.func_native(_FMA_SNIPPET)
def fmaf(a: float, b: float, c: float) -> float: ...


def _vec(n):
    return wp.float32 if n == 1 else wp.types.vector(length=n, dtype=wp.float32)


def _hvec(n):
    return wp.float16 if n == 1 else wp.types.vector(length=n, dtype=wp.float16)


class _IO(NamedTuple):
    V: type  # F floats
    VP: type  # 2F floats (an x-pair of entries)
    gather: object  # (params: array(V), e) -> V, read-only path
    load_stream: object  # (a: array(V), e) -> V, evict-first
    store: object  # (o: array(V), e, v: V), evict-first
    store_bf16: object  # (o: array(int16), e, v: V), F bfloat16s at e * F, evict-first
    red: object  # (g: array(V), e, v: V)
    red_pair: object  # (g: array(V), e, v: VP)
    red_half: object  # (g: array(VH), e, v: V)
    red_half_pair: object  # (g: array(VH), e, v: VP)


@functools.cache
def _io(n_features):
    """Native memory helpers for F-feature entries (overloads distinguished by the array types)."""
    F = n_features
    V, VP, VH = _vec(F), _vec(2 * F), _hvec(F)
    pair_ok = 2 * F <= 4

    s_gather = _load_snippet(F, "p", "nc")
    s_stream = _load_snippet(F, "a", "cs")
    s_store = _store_snippet(F)
    s_store_bf16 = _store_bf16_snippet(F)
    s_red = _red_snippet(F)
    s_red_pair = _red_snippet(2 * F, F)  # entries e and e + 1
    s_red_half = _red_half_snippet(F)
    s_red_half_pair = _red_half_snippet(2 * F, F)

    @wp.func_native(s_gather)
    def gather(p: wp.array(dtype=V), e: wp.uint32) -> V: ...

    @wp.func_native(s_stream)
    def load_stream(a: wp.array(dtype=V), e: int) -> V: ...

    @wp.func_native(s_store)
    def store(o: wp.array(dtype=V), e: int, v: V): ...

    @wp.func_native(s_store_bf16)
    def store_bf16(o: wp.array(dtype=wp.int16), e: int, v: V): ...

    @wp.func_native(s_red)
    def red(g: wp.array(dtype=V), e: wp.uint32, v: V): ...

    @wp.func_native(s_red_half)
    def red_half(g: wp.array(dtype=VH), e: wp.uint32, v: V): ...

    red_pair = red_half_pair = None
    if pair_ok:

        @wp.func_native(s_red_pair)
        def red_pair(g: wp.array(dtype=V), e: wp.uint32, v: VP): ...

        @wp.func_native(s_red_half_pair)
        def red_half_pair(g: wp.array(dtype=VH), e: wp.uint32, v: VP): ...

    return _IO(V, VP, gather, load_stream, store, store_bf16, red, red_pair, red_half, red_half_pair)


# ---------------------------------------------------------------------------------------------
# kernels
# ---------------------------------------------------------------------------------------------


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
    D, F, interp, G, K, paired, half_grad, GX = config
    if D not in (2, 3):
        raise ValueError(f"n_dims must be 2 or 3, got {D}")
    if F not in (1, 2, 4, 8):
        raise ValueError(f"n_features must be 1, 2, 4 or 8, got {F}")
    if interp not in INTERPOLATIONS:
        raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, got {interp!r}")
    if G < 1 or K < 1 or GX < 0:
        raise ValueError("levels_per_thread and level_lanes must be >= 1, dx_levels_per_thread >= 0")
    paired = bool(paired) and F <= 2

    io = _io(F)
    V, VP, VH = io.V, io.VP, _hvec(F)
    gather, load_stream, store, store_bf16 = io.gather, io.load_stream, io.store, io.store_bf16
    red, red_pair, red_half, red_half_pair = io.red, io.red_pair, io.red_half, io.red_half_pair
    VU = wp.types.vector(length=D, dtype=wp.uint32)
    VD = wp.types.vector(length=D, dtype=wp.float32)
    NC = 1 << D  # corners per cell
    NH = NC // 2  # x-pairs of corners
    VI = wp.types.vector(length=NC, dtype=wp.uint32)
    SMOOTH = interp == SMOOTHSTEP
    KG = K * G  # levels per level group
    module = f"ngp_warp.hashgrid.D{D}F{F}{interp[0]}G{G}K{K}p{int(paired)}h{int(half_grad)}x{GX}"

    @wp.func
    def locate(x: wp.array(dtype=wp.float32), p: int, scale: float):
        """Cell coordinates, upper-corner weights and their derivatives along each dim."""
        g = VU()
        w = VD()
        dw = VD()
        for d in range(D):
            pos = fmaf(scale, x[p * D + d], 0.5)
            t = wp.floor(pos)
            g[d] = wp.uint32(wp.int32(t))
            fr = pos - t
            if wp.static(SMOOTH):
                w[d] = fr * fr * (3.0 - 2.0 * fr)
                dw[d] = 6.0 * fr * (1.0 - fr)
            else:
                w[d] = fr
                dw[d] = 1.0
        return g, w, dw

    @wp.func
    def corner_indices(g: VU, res: wp.uint32, size: wp.uint32, hashed: int):
        """Entry indices (within the level) of the 2^D corners; bit d of c: upper along dim d.

        Branch-free in the common case, so that the compiler can issue all the corners' loads
        back to back: hashed levels XOR ``coord_d * prime_d``, dense ones add ``coord_d *
        res^d``, both in wrapping uint32. The table size is a power of two except on some
        dense levels, whose rare out-of-table indices (cells on the upper faces, points
        outside [0, 1]) take tcnn's ``index % size`` in a separate pass.
        """
        is_hashed = hashed != 0
        # per-dim multiplier: the hash prime or the dense stride (the x prime is 1)
        m1 = wp.where(is_hashed, _P1, res)
        a0 = VU()
        a1 = VU()
        a0[0] = g[0]
        a1[0] = g[0] + wp.uint32(1)
        a0[1] = g[1] * m1
        a1[1] = a0[1] + m1
        if wp.static(D == 3):
            m2 = wp.where(is_hashed, _P2, res * res)
            a0[2] = g[2] * m2
            a1[2] = a0[2] + m2
        mask = size - wp.uint32(1)
        folded = is_hashed or (size & mask) == wp.uint32(0)  # index & mask == index % size
        if not folded:
            mask = _ALL_BITS
        idx = VI()
        for c in range(NC):
            t0 = a0[0]
            if (c & 1) != 0:
                t0 = a1[0]
            t1 = a0[1]
            if (c & 2) != 0:
                t1 = a1[1]
            h = t0 ^ t1
            s = t0 + t1
            if wp.static(D == 3):
                t2 = a0[2]
                if (c & 4) != 0:
                    t2 = a1[2]
                h = h ^ t2
                s = s + t2
            idx[c] = wp.where(is_hashed, h, s) & mask
        if not folded:
            for c in range(NC):
                if idx[c] >= size:
                    idx[c] = idx[c] % size
        return idx

    @wp.func
    def corner_weight(w: VD, c: int):
        wc = float(1.0)
        for d in range(D):
            if ((c >> d) & 1) != 0:
                wc = wc * w[d]
            else:
                wc = wc * (1.0 - w[d])
        return wc

    @wp.func
    def join_pair(a: V, b: V, odd_first: bool):
        """Values for (lower-x corner, upper-x corner) -> vector for entries (e, e+1)."""
        vp = VP()
        u = a
        v = b
        if odd_first:
            u = b
            v = a
        if wp.static(F == 1):
            vp[0] = u
            vp[1] = v
        else:
            for f in range(F):
                vp[f] = u[f]
                vp[F + f] = v[f]
        return vp

    @wp.func
    def encode_level(
        x: wp.array(dtype=wp.float32),
        p: int,
        params: wp.array(dtype=V),
        scale: float,
        m: wp.vec4i,
    ):
        res = wp.uint32(m[0])
        off = wp.uint32(m[1])
        size = wp.uint32(m[2])
        hashed = m[3]
        g, w, dw = locate(x, p, scale)
        idx = corner_indices(g, res, size, hashed)
        acc = V(0.0)
        for c in range(NC):
            acc += corner_weight(w, c) * gather(params, off + idx[c])
        return acc

    @wp.func
    def schedule(item: int, n: int):
        """item -> (level group, point, lane): lanes are the fastest-varying index."""
        kn = K * n
        grp = item // kn
        r = item - grp * kn
        p = r // K
        return grp, p, r - p * K

    @wp.kernel(enable_backward=False, module=module, grid_stride=False)
    def forward(
        first: int,
        n: int,
        n_levels: int,
        x: wp.array(dtype=wp.float32),
        params: wp.array(dtype=V),
        scales: wp.array(dtype=wp.float32),
        meta: wp.array(dtype=wp.vec4i),
        out: wp.array(dtype=V),
    ):
        grp, p, lane = schedule(first + wp.tid(), n)
        for j in range(G):
            level = grp * KG + j * K + lane
            if level < n_levels:
                store(out, p * n_levels + level, encode_level(x, p, params, scales[level], meta[level]))

    @wp.kernel(enable_backward=False, module=module, grid_stride=False)
    def forward_bf16(
        first: int,
        n: int,
        n_levels: int,
        x: wp.array(dtype=wp.float32),
        params: wp.array(dtype=V),
        scales: wp.array(dtype=wp.float32),
        meta: wp.array(dtype=wp.vec4i),
        out: wp.array(dtype=wp.int16),
    ):
        # forward's features rounded to bfloat16: half the bytes written, no cast after
        grp, p, lane = schedule(first + wp.tid(), n)
        for j in range(G):
            level = grp * KG + j * K + lane
            if level < n_levels:
                store_bf16(out, p * n_levels + level, encode_level(x, p, params, scales[level], meta[level]))

    @wp.func
    def scatter(
        grad: wp.array(dtype=V),
        grad_half: wp.array(dtype=VH),
        use_half: bool,
        e: wp.uint32,
        half_base: wp.uint32,
        v: V,
    ):
        if wp.static(half_grad):
            if use_half:
                red_half(grad_half, e - half_base, v)
                return
        red(grad, e, v)

    @wp.func
    def scatter_pair(
        grad: wp.array(dtype=V),
        grad_half: wp.array(dtype=VH),
        use_half: bool,
        e: wp.uint32,
        half_base: wp.uint32,
        v: VP,
    ):
        if wp.static(half_grad):
            if use_half:
                red_half_pair(grad_half, e - half_base, v)
                return
        red_pair(grad, e, v)

    @wp.func
    def any_nonzero(v: V) -> bool:
        if wp.static(F == 1):
            return v != 0.0
        else:
            hit = False
            for k in range(F):
                hit = hit or v[k] != 0.0
            return hit

    @wp.kernel(enable_backward=False, module=module, grid_stride=False)
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

    @wp.func
    def dot_f(a: V, b: V):
        if wp.static(F == 1):
            return a * b
        else:
            return wp.dot(a, b)

    @wp.func
    def level_dx(
        x: wp.array(dtype=wp.float32),
        p: int,
        params: wp.array(dtype=V),
        scale: float,
        m: wp.vec4i,
        go: V,
    ):
        """d(go . encode_level(x)) / dx for one level."""
        res = wp.uint32(m[0])
        off = wp.uint32(m[1])
        size = wp.uint32(m[2])
        hashed = m[3]
        g, w, dw = locate(x, p, scale)
        idx = corner_indices(g, res, size, hashed)
        acc = VD()
        for c in range(NC):
            s = dot_f(go, gather(params, off + idx[c]))
            for d in range(D):
                # d weight(c) / d w[d]: the other dims' factors, signed by corner bit d
                wd = float(1.0)
                for e in range(D):
                    if e != d:
                        if ((c >> e) & 1) != 0:
                            wd = wd * w[e]
                        else:
                            wd = wd * (1.0 - w[e])
                if ((c >> d) & 1) != 0:
                    acc[d] = acc[d] + s * wd
                else:
                    acc[d] = acc[d] - s * wd
        for d in range(D):
            acc[d] = acc[d] * (scale * dw[d])
        return acc

    @wp.kernel(enable_backward=False, module=module, grid_stride=False)
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

    return Kernels(config, forward, forward_bf16, backward_params, backward_x)
