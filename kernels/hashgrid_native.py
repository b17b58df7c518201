"""Native (C++ / inline PTX) memory helpers of the hash-grid kernels (``kernels/hashgrid.py``).

Warp's kernel language has no cache hints or vector reductions, so the hash grid reads and
writes memory through small ``wp.func_native`` snippets, generated here per feature count
``F`` (an entry is ``F`` float32s, a ``vec_t<F, float32>``; a float32 scalar for ``F = 1``):

* ``gather(p, e)``: entry ``e`` of the table ``p`` through the read-only (non-coherent) path,
  ``ld.global.nc.v4.f32`` and narrower;
* ``load_stream(a, e)`` / ``store(o, e, v)``: streaming (evict-first, ``.cs``) load and store of
  entry ``e`` of the output or its gradient, so that they do not push the tables out of L2;
* ``store_bf16(o, e, v)``: ``v`` rounded to bfloat16 (to nearest, ties to even) stored at
  bfloat16 offset ``e * F``: packed ``cvt.rn.bf16x2.f32`` on sm_80 and later, the same
  rounding on the bits elsewhere ``(u + 0x7FFF + ((u >> 16) & 1)) >> 16``, NaN -> ``0x7FC0``;
* ``red(g, e, v)``: ``g[e] += v``; sm_90: vector reductions ``red.global.v2/v4.f32.add`` (one
  per entry instead of one per float); older GPUs: one ``atomicAdd`` per float; CPU: plain
  (non-atomic) additions;
* ``red_half(g, e, v)``: the same into a float16 table, ``v`` rounded to half
  (``cvt.rn.f16x2.f32`` then ``red.global.add.noftz.f16x2``, vectors of them on sm_90);
* ``red_pair`` / ``red_half_pair``: the same for ``2F`` floats at entries ``e`` and ``e + 1``
  (for ``2F <= 4``: one 16-byte reduction for the two x-neighbouring corners of a cell).

Every snippet has a plain C++ branch, so the same kernels compile for the CPU.
"""

import functools
from typing import NamedTuple

import warp as wp


def vec_type(n: int):
    """Warp type of ``n`` float32s: ``wp.float32`` for one, else a length-``n`` vector."""
    return wp.float32 if n == 1 else wp.types.vector(length=n, dtype=wp.float32)


def half_vec_type(n: int):
    """Warp type of ``n`` float16s: ``wp.float16`` for one, else a length-``n`` vector."""
    return wp.float16 if n == 1 else wp.types.vector(length=n, dtype=wp.float16)


def _regs(n, first=0):
    return ", ".join(f"%{first + i}" for i in range(n))


def _components(n):
    """C++ expressions of the ``n`` floats of the snippet argument ``v``."""
    return ["v"] if n == 1 else [f"v.c[{i}]" for i in range(n)]


def _load_snippet(n, arr, cache):
    """C++ body returning ``n`` floats read at float offset ``e * n`` of ``arr``."""
    ct = "wp::float32" if n == 1 else f"wp::vec_t<{n}, wp::float32>"
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
    vals = _components(n)
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
    vals = _components(n)
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
    vals = _components(n)
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
    vals = _components(n)
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
                red = "red.global.add.noftz.f16x2 [%0], %1;"
            else:
                red = f"red.global.v{w}.f16x2.add.noftz [%0], {{{_regs(w, 1)}}};"
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


# a * b + c rounded once, as tiny-cuda-nn places points on a level's grid
@wp.func_native(_FMA_SNIPPET)
def fmaf(a: float, b: float, c: float) -> float: ...


class NativeIO(NamedTuple):
    """The memory helpers of one feature count ``F`` (see the module docstring)."""

    gather: object  # (p: array(V), e: uint32) -> V
    load_stream: object  # (a: array(V), e: int) -> V
    store: object  # (o: array(V), e: int, v: V)
    store_bf16: object  # (o: array(int16), e: int, v: V)
    red: object  # (g: array(V), e: uint32, v: V)
    red_half: object  # (g: array(VH), e: uint32, v: V)
    red_pair: object  # (g: array(V), e: uint32, v: VP); None when 2F > 4
    red_half_pair: object  # (g: array(VH), e: uint32, v: VP); None when 2F > 4


@functools.cache
def native_io(n_features: int) -> NativeIO:
    """Native memory helpers for ``n_features``-float entries: ``V`` is :func:`vec_type` of
    ``F``, ``VP`` of ``2F`` (an x-pair of entries), ``VH`` :func:`half_vec_type` of ``F``."""
    F = n_features
    V, VP, VH = vec_type(F), vec_type(2 * F), half_vec_type(F)

    @wp.func_native(_load_snippet(F, "p", "nc"))
    def gather(p: wp.array(dtype=V), e: wp.uint32) -> V: ...

    @wp.func_native(_load_snippet(F, "a", "cs"))
    def load_stream(a: wp.array(dtype=V), e: int) -> V: ...

    @wp.func_native(_store_snippet(F))
    def store(o: wp.array(dtype=V), e: int, v: V): ...

    @wp.func_native(_store_bf16_snippet(F))
    def store_bf16(o: wp.array(dtype=wp.int16), e: int, v: V): ...

    @wp.func_native(_red_snippet(F))
    def red(g: wp.array(dtype=V), e: wp.uint32, v: V): ...

    @wp.func_native(_red_half_snippet(F))
    def red_half(g: wp.array(dtype=VH), e: wp.uint32, v: V): ...

    red_pair = red_half_pair = None
    if 2 * F <= 4:

        @wp.func_native(_red_snippet(2 * F, F))  # entries e and e + 1
        def red_pair(g: wp.array(dtype=V), e: wp.uint32, v: VP): ...

        @wp.func_native(_red_half_snippet(2 * F, F))
        def red_half_pair(g: wp.array(dtype=VH), e: wp.uint32, v: VP): ...

    return NativeIO(gather, load_stream, store, store_bf16, red, red_half, red_pair, red_half_pair)
