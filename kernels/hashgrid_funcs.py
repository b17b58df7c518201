"""Warp functions shared by the hash-grid kernels (``kernels/hashgrid.py``).

Each factory bakes in the configuration values its code branches or unrolls on (``D``: the
dimension, ``F``: features per entry, the interpolation, ``K``: lanes per point), so that the
compiler sees constant loop bounds; :func:`ngp_warp.kernels.hashgrid.get_kernels` calls them
once per kernel configuration. Types: ``VU`` / ``VD`` are ``D`` uint32s / float32s, ``V`` an
entry (``F`` float32s, a scalar for ``F = 1``), ``VP`` an x-pair of entries (``2F`` float32s),
``VI`` the ``2^D`` corner indices (uint32).
"""

import warp as wp

from ngp_warp.kernels.hashgrid_native import fmaf, half_vec_type, vec_type

PRIMES = (1, 2654435761, 805459861)  # spatial-hash primes of x, y, z
_P1 = wp.constant(wp.uint32(PRIMES[1]))
_P2 = wp.constant(wp.uint32(PRIMES[2]))
_ALL_BITS = wp.constant(wp.uint32(0xFFFFFFFF))


def locate_func(D: int, smooth: bool):
    """``locate(x, p, scale) -> (g: VU, w: VD, dw: VD)`` for point ``p`` of the flat ``[N*D]``
    float32 ``x``: ``pos = fmaf(scale, x, 0.5)``, cell ``g = floor(pos)`` (uint32, wrapping
    below 0), upper-corner weight ``w = t`` or ``t^2 (3 - 2t)`` of ``t = pos - g`` and
    ``dw = dw/dt``."""
    VU = wp.types.vector(length=D, dtype=wp.uint32)
    VD = wp.types.vector(length=D, dtype=wp.float32)

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
            if wp.static(smooth):
                w[d] = fr * fr * (3.0 - 2.0 * fr)
                dw[d] = 6.0 * fr * (1.0 - fr)
            else:
                w[d] = fr
                dw[d] = 1.0
        return g, w, dw

    return locate


def corner_funcs(D: int):
    """``(corner_indices(g, res, size, hashed) -> VI, corner_weight(w, c) -> float)``.

    Corner ``c`` of a cell (bit ``d`` of ``c``: upper along dim ``d``) has the entry
    ``(g_x ^ g_y * 2654435761 ^ g_z * 805459861) mod size`` on hashed levels and ``(g_x + g_y *
    res + g_z * res^2) mod size`` on dense ones (uint32 arithmetic) and the weight
    ``prod_d (w_d if bit d else 1 - w_d)``.
    """
    VU = wp.types.vector(length=D, dtype=wp.uint32)
    VD = wp.types.vector(length=D, dtype=wp.float32)
    NC = 1 << D  # corners per cell
    VI = wp.types.vector(length=NC, dtype=wp.uint32)

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

    return corner_indices, corner_weight


def feature_funcs(F: int):
    """``(join_pair(a, b, odd_first) -> VP, any_nonzero(v) -> bool, dot_f(a, b) -> float)`` on
    entries ``V`` of ``F`` float32s."""
    V, VP = vec_type(F), vec_type(2 * F)

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
    def any_nonzero(v: V) -> bool:
        if wp.static(F == 1):
            return v != 0.0
        else:
            hit = False
            for k in range(F):
                hit = hit or v[k] != 0.0
            return hit

    @wp.func
    def dot_f(a: V, b: V):
        if wp.static(F == 1):
            return a * b
        else:
            return wp.dot(a, b)

    return join_pair, any_nonzero, dot_f


def level_funcs(D: int, F: int, locate, corner_indices, corner_weight, dot_f, gather):
    """``(encode_level(x, p, params, scale, m) -> V, level_dx(x, p, params, scale, m, go) -> VD)``
    for one level (``m``: its ``vec4i`` of (resolution, offset, entries, hashed flag)):

    ``encode_level = sum_c weight_c * params[offset + index_c]`` and ``level_dx = d(go .
    encode_level) / dx``, whose component ``d`` is ``scale * dw_d * sum_c (go . params[..c]) *
    (+-1 by bit d of c) * prod_{e != d} (w_e or 1 - w_e)``.
    """
    V = vec_type(F)
    VD = wp.types.vector(length=D, dtype=wp.float32)
    NC = 1 << D

    @wp.func
    def encode_level(x: wp.array(dtype=wp.float32), p: int, params: wp.array(dtype=V), scale: float, m: wp.vec4i):
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
    def level_dx(
        x: wp.array(dtype=wp.float32), p: int, params: wp.array(dtype=V), scale: float, m: wp.vec4i, go: V
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

    return encode_level, level_dx


def schedule_func(K: int):
    """``schedule(item, n) -> (level group, point, lane)`` for ``K`` lanes per point: the ``K*n``
    items of a level group run point by point, lanes the fastest-varying index."""

    @wp.func
    def schedule(item: int, n: int):
        """item -> (level group, point, lane): lanes are the fastest-varying index."""
        kn = K * n
        grp = item // kn
        r = item - grp * kn
        p = r // K
        return grp, p, r - p * K

    return schedule


def scatter_func(F: int, value_type, red, red_half, half_grad: bool):
    """``scatter(grad, grad_half, use_half, e, half_base, v)``: adds ``v`` (a ``value_type``:
    one entry, or an x-pair of entries through the pair reductions) at entry ``e`` of the
    float32 table gradient ``grad``, or, with ``half_grad`` and ``use_half``, at entry ``e -
    half_base`` of the float16 one ``grad_half``."""
    V, VH = vec_type(F), half_vec_type(F)

    @wp.func
    def scatter(
        grad: wp.array(dtype=V),
        grad_half: wp.array(dtype=VH),
        use_half: bool,
        e: wp.uint32,
        half_base: wp.uint32,
        v: value_type,
    ):
        if wp.static(half_grad):
            if use_half:
                red_half(grad_half, e - half_base, v)
                return
        red(grad, e, v)

    return scatter
