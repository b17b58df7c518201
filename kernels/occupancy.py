"""Occupancy-grid kernels: cascade geometry, cell sampling, max-EMA update, bitfield packing,
visibility marking, and the refresh's test of what the training cameras see.

Layout shared with :mod:`ngp_warp.kernels.raymarch`. ``aabb = (min_xyz, max_xyz)`` is the base box
with centre ``c`` and half extent ``h``; cascade ``l`` covers ``c ± h·2^l``. Each level is an
``R³`` grid of cells; cell ``(l, i, j, k)`` has linear id ``((l·R + i)·R + j)·R + k`` and its
occupancy is bit ``id & 7`` of byte ``id >> 3`` of the bitfield. A point belongs to the finest
cascade whose box contains it.

Mip ``m`` (1 ≤ m ≤ n_mips, ``R % 2^n_mips = 0``) of cascade ``l`` holds one byte per block of
``2^m × 2^m × 2^m`` cells, nonzero unless the march may jump over the whole block: block
``(a, b, c)`` of mip ``m`` of level ``l`` is byte ``l·mip_cells + base_m + (a·R_m + b)·R_m + c``
with ``R_m = R >> m`` and ``base_m = Σ_{m' < m} R_{m'}³``.
"""

import warp as wp

from ngp_warp.kernels.contraction import denormalize_point, uncontract

wp.set_module_options({"enable_backward": False})

# Bisection over at most 2^31 cells ends within 31 halvings.
_BISECT_STEPS = wp.constant(31)


@wp.func
def box_center(aabb: wp.array(dtype=float)) -> wp.vec3:
    return wp.vec3(aabb[0] + aabb[3], aabb[1] + aabb[4], aabb[2] + aabb[5]) * 0.5


@wp.func
def box_half(aabb: wp.array(dtype=float)) -> wp.vec3:
    return wp.vec3(aabb[3] - aabb[0], aabb[4] - aabb[1], aabb[5] - aabb[2]) * 0.5


@wp.func
def cascade_of(p: wp.vec3, c: wp.vec3, h: wp.vec3, levels: int) -> int:
    """Finest level l with |p − c| ≤ h·2^l on every axis (the coarsest one if none)."""
    q = p - c
    level = levels - 1
    found = int(0)
    scale = float(1.0)
    for l in range(levels):
        inside = wp.abs(q[0]) <= h[0] * scale and wp.abs(q[1]) <= h[1] * scale and wp.abs(q[2]) <= h[2] * scale
        if inside and found == 0:
            level = l
            found = 1
        scale = scale * 2.0
    return level


@wp.func
def cell_id(level: int, ijk: wp.vec3i, res: int) -> int:
    return ((level * res + ijk[0]) * res + ijk[1]) * res + ijk[2]


@wp.func
def cell_lower(c: wp.vec3, h: wp.vec3, level: int, ijk: wp.vec3i, res: int) -> wp.vec3:
    """World-space lower corner of a cell."""
    s = h * float(1 << level)
    size = s * (2.0 / float(res))
    return c - s + wp.cw_mul(wp.vec3(float(ijk[0]), float(ijk[1]), float(ijk[2])), size)


@wp.func
def is_occupied(bitfield: wp.array(dtype=wp.uint8), cell: int) -> bool:
    return ((int(bitfield[cell >> 3]) >> (cell & 7)) & 1) != 0


@wp.func
def decode_cell(cell: int, res: int) -> wp.vec4i:
    """Linear cell id → (level, i, j, k)."""
    per_level = res * res * res
    rem = cell % per_level
    return wp.vec4i(cell // per_level, rem // (res * res), (rem // res) % res, rem % res)


# Sample one point per requested cell. Item i (global index g = offset + i):
#   warm-up:           cell = g (every cell once, in order)
#   g < n_uniform:     cell ~ U{0 .. n_cells-1}
#   otherwise:         cell = k-th occupied cell, k ~ U{0 .. n_occ-1}, found by bisection of the
#                      inclusive prefix count of occupied cells (uniform when none is occupied)
#   point = lower corner + u ⊙ cell size, u ~ U[0,1)^3.
@wp.kernel
def sample_cells(
    first: int,
    offset: int,
    warmup: int,
    n_uniform: int,
    n_cells: int,
    seed: int,
    occupied_prefix: wp.array(dtype=wp.int32),
    aabb: wp.array(dtype=float),
    res: int,
    cells: wp.array(dtype=wp.int32),
    points: wp.array(dtype=wp.vec3),
):
    i = first + wp.tid()
    g = offset + i
    state = wp.rand_init(seed, g)
    cell = g
    if warmup == 0:
        cell = wp.randi(state, 0, n_cells)
        n_occ = int(occupied_prefix[n_cells - 1])
        if g >= n_uniform and n_occ > 0:
            k = wp.randi(state, 0, n_occ)
            lo = int(0)
            hi = n_cells - 1
            for _ in range(_BISECT_STEPS):
                if lo < hi:
                    mid = (lo + hi) // 2
                    if int(occupied_prefix[mid]) > k:
                        hi = mid
                    else:
                        lo = mid + 1
            cell = lo
    lijk = decode_cell(cell, res)
    ijk = wp.vec3i(lijk[1], lijk[2], lijk[3])
    c = box_center(aabb)
    h = box_half(aabb)
    size = h * (float(1 << lijk[0]) * 2.0 / float(res))
    u = wp.vec3(wp.randf(state), wp.randf(state), wp.randf(state))
    cells[i] = cell
    points[i] = cell_lower(c, h, lijk[0], ijk, res) + wp.cw_mul(u, size)


# splat[cell_i] = max(splat[cell_i], max(value_i, 0))   (scatter-max; splat starts at -1)
@wp.kernel
def splat_max(
    first: int,
    cells: wp.array(dtype=wp.int32),
    values: wp.array(dtype=float),
    splat: wp.array(dtype=float),
):
    i = first + wp.tid()
    wp.atomic_max(splat, cells[i], wp.max(values[i], 0.0))


# Sampled, visible cells: occ ← max(occ·decay, splat). Invisible cells (occ < 0) stay put.
# splat is reset to -1 for the next update.
@wp.kernel
def ema_update(
    first: int,
    splat: wp.array(dtype=float),
    decay: float,
    occs: wp.array(dtype=float),
):
    i = first + wp.tid()
    s = splat[i]
    old = occs[i]
    if s >= 0.0 and old >= 0.0:
        occs[i] = wp.max(old * decay, s)
    splat[i] = -1.0


# bit b of byte i = occs[8i + b] > threshold
@wp.kernel
def pack_bitfield(
    first: int,
    occs: wp.array(dtype=float),
    threshold: wp.array(dtype=float),
    n_cells: int,
    bitfield: wp.array(dtype=wp.uint8),
):
    i = first + wp.tid()
    thr = threshold[0]
    bits = int(0)
    for b in range(8):
        cell = i * 8 + b
        if cell < n_cells:
            if occs[cell] > thr:
                bits = bits | (1 << b)
    bitfield[i] = wp.uint8(bits)


# Mip m from the level below (mip 0 = the bitfield): a block is marked when any of its 8
# sub-blocks is, or (m = 1, l ≥ 1) when it overlaps the box of cascade l − 1 (cells
# R/4 .. 3R/4 − 1 on every axis), whose points the march must classify with the finer cascade.
@wp.kernel
def pack_mip(
    first: int,
    bitfield: wp.array(dtype=wp.uint8),
    res: int,
    m: int,
    mip_cells: int,
    base_child: int,
    base: int,
    mips: wp.array(dtype=wp.uint8),
):
    i = first + wp.tid()
    rm = res >> m
    per_level = rm * rm * rm
    level = i // per_level
    rem = i - level * per_level
    blk = wp.vec3i(rem // (rm * rm), (rem // rm) % rm, rem % rm)
    marked = int(0)
    for q in range(8):
        child = wp.vec3i(2 * blk[0] + (q & 1), 2 * blk[1] + ((q >> 1) & 1), 2 * blk[2] + (q >> 2))
        if m == 1:
            if is_occupied(bitfield, cell_id(level, child, res)):
                marked = 1
        else:
            rc = 2 * rm
            if int(mips[level * mip_cells + base_child + (child[0] * rc + child[1]) * rc + child[2]]) != 0:
                marked = 1
    if m == 1 and level > 0:
        inner = int(1)
        for a in range(3):
            if 2 * blk[a] + 2 <= res // 4 or 2 * blk[a] >= 3 * res // 4:
                inner = 0
        marked = marked | inner
    mips[level * mip_cells + base + rem] = wp.uint8(marked)


@wp.func
def project(p: wp.vec3, c2w: wp.array2d(dtype=float), intr: wp.array2d(dtype=float), cam: int) -> wp.vec4:
    """OpenGL camera (looks down −z, +y up): (u, v, depth, distance) with u = fx·x/(−z) + cx,
    v = cy − fy·y/(−z), depth = −z; u and v are 0 behind the camera (depth ≤ 0)."""
    d = wp.vec3(p[0] - c2w[cam, 3], p[1] - c2w[cam, 7], p[2] - c2w[cam, 11])
    x = c2w[cam, 0] * d[0] + c2w[cam, 4] * d[1] + c2w[cam, 8] * d[2]
    y = c2w[cam, 1] * d[0] + c2w[cam, 5] * d[1] + c2w[cam, 9] * d[2]
    depth = -(c2w[cam, 2] * d[0] + c2w[cam, 6] * d[1] + c2w[cam, 10] * d[2])
    u = float(0.0)
    v = float(0.0)
    if depth > 0.0:
        u = intr[cam, 0] * x / depth + intr[cam, 2]
        v = intr[cam, 3] - intr[cam, 1] * y / depth
    return wp.vec4(u, v, depth, wp.length(d))


@wp.func
def corner_seen(p: wp.vec3, c2w: wp.array2d(dtype=float), intr: wp.array2d(dtype=float), cam: int,
                width: float, height: float, near_plane: float) -> bool:
    """In camera ``cam``'s image (0 ≤ u ≤ width, 0 ≤ v ≤ height), in front of its near plane."""
    q = project(p, c2w, intr, cam)
    return q[2] > near_plane and q[2] > 0.0 and q[0] >= 0.0 and q[0] <= width and q[1] >= 0.0 and q[1] <= height


# A cell is visible when any of its 8 corners projects into any camera's image in front of its
# near plane. occ ← visible ? max(occ, 0) : -1. With a contraction (kind ≥ 0) the grid is in
# contracted space: corner y is seen at the world point c_in + h_in ⊙ C⁻¹(y).
@wp.kernel
def mark_visible(
    first: int,
    aabb: wp.array(dtype=float),
    res: int,
    kind: int,
    inner_aabb: wp.array(dtype=float),
    c2w: wp.array2d(dtype=float),
    intr: wp.array2d(dtype=float),
    n_cams: int,
    width: float,
    height: float,
    near_plane: float,
    occs: wp.array(dtype=float),
):
    i = first + wp.tid()
    lijk = decode_cell(i, res)
    c = box_center(aabb)
    h = box_half(aabb)
    size = h * (float(1 << lijk[0]) * 2.0 / float(res))
    lo = cell_lower(c, h, lijk[0], wp.vec3i(lijk[1], lijk[2], lijk[3]), res)
    visible = int(0)
    cam = int(0)
    while cam < n_cams and visible == 0:
        for corner in range(8):
            p = lo + wp.cw_mul(wp.vec3(float(corner & 1), float((corner >> 1) & 1), float(corner >> 2)), size)
            if kind >= 0:
                p = denormalize_point(uncontract(p, kind), inner_aabb)
            if corner_seen(p, c2w, intr, cam, width, height, near_plane):
                visible = 1
        cam += 1
    if visible != 0:
        occs[i] = wp.max(occs[i], 0.0)
    else:
        occs[i] = -1.0


# Density that no training ray samples holds no cell: a refresh's sample point p counts only where
# some training camera sees it, σ ← seen(p) ? σ : 0, with seen(p) = ∃ camera: depth > 0,
# |p − o| > near (its rays start there), −m ≤ u ≤ W + m and −m ≤ v ≤ H + m (m covers the pinhole
# projection's error at the border of a distorted image). Cells that an image holds only at its
# border would otherwise fill with what the field extrapolates beside the image, which held-out
# views see as floaters.
@wp.kernel
def zero_unseen(
    first: int,
    points: wp.array(dtype=wp.vec3),
    c2w: wp.array2d(dtype=float),
    intr: wp.array2d(dtype=float),
    n_cams: int,
    width: float,
    height: float,
    near: float,
    margin: float,
    values: wp.array(dtype=float),
):
    i = first + wp.tid()
    p = points[i]
    seen = int(0)
    cam = int(0)
    while cam < n_cams and seen == 0:
        q = project(p, c2w, intr, cam)
        if q[2] > 0.0 and q[3] > near and q[0] >= -margin and q[0] <= width + margin:
            if q[1] >= -margin and q[1] <= height + margin:
                seen = 1
        cam += 1
    if seen == 0:
        values[i] = 0.0
