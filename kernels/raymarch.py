"""Ray marching through an occupancy grid, run twice: count, then fill.

With fixed steps a ray's steps are split into segments of ``seg_steps`` steps, each marched by
its own thread (the last one runs to the ray's end); with cone steps one thread marches a ray.
The kernel is built from the helpers below: the ray's interval (:func:`ray_span`), the step
size (:func:`step_at`), the cell lookup (:func:`grid_cell`), the walk through an occupied cell
(:func:`take_cell`) and the jump over empty space (:func:`skip_empty`).
Sampling carries no gradient, so there is no backward kernel here.
"""

import warp as wp

from ngp_warp.kernels.occupancy import box_center, box_half, cascade_of, cell_id, is_occupied

wp.set_module_options({"enable_backward": False})

_FAR = wp.constant(1.0e30)
# Loop iterations per ray never exceed this (ends degenerate rays, e.g. near-zero directions
# whose t range float32 steps cannot resolve); sane rays need far fewer (~1024·2^levels).
_MAX_ITERS = wp.constant(1 << 24)
# A step mask with every bit set means "march again" (see march_rays).
_REMARCH = wp.constant(wp.uint64(0xFFFFFFFFFFFFFFFF))


@wp.struct
class MarchConfig:
    """The march's settings: grid (res, levels, n_mips, mip_cells), ray interval and steps, the
    per-ray cap, stratification and the segments per ray (one value per batch, so the host
    builds it once per configuration)."""

    res: int
    levels: int
    n_mips: int
    mip_cells: int
    near: float
    far: float
    step: float
    cone: float
    max_step: float
    max_per_ray: int
    stratified: int
    n_seg: int
    seg_steps: int


@wp.func
def ray_box(o: wp.vec3, d: wp.vec3, lo: wp.vec3, hi: wp.vec3) -> wp.vec2:
    """Slab test: (t_enter, t_exit) of o + t·d with the box; t_enter > t_exit on a miss."""
    t_enter = -_FAR
    t_exit = _FAR
    for a in range(3):
        if d[a] != 0.0:
            ta = (lo[a] - o[a]) / d[a]
            tb = (hi[a] - o[a]) / d[a]
            t_enter = wp.max(t_enter, wp.min(ta, tb))
            t_exit = wp.min(t_exit, wp.max(ta, tb))
        elif o[a] < lo[a] or o[a] > hi[a]:
            t_exit = -_FAR
    return wp.vec2(t_enter, t_exit)


@wp.func
def ray_span(o: wp.vec3, d: wp.vec3, c: wp.vec3, h: wp.vec3, cfg: MarchConfig) -> wp.vec2:
    """[t0, t1] = [max(near, t_enter), min(far, t_exit)] of the ray with the coarsest cascade's
    box c ± h·2^(levels−1); t0 ≥ t1 when the ray misses it."""
    outer = h * float(1 << (cfg.levels - 1))
    hit = ray_box(o, d, c - outer, c + outer)
    return wp.vec2(wp.max(hit[0], cfg.near), wp.min(hit[1], cfg.far))


@wp.func
def step_at(t: float, step: float, cone: float, max_step: float) -> float:
    """Δt = step (cone = 0) or clamp(t·cone, step, max_step)."""
    dt = step
    if cone > 0.0:
        dt = wp.clamp(t * cone, step, max_step)
    return dt


@wp.func
def march_start(t0: float, dt: float, stratified: int, seed: int, r: int) -> float:
    """t_s = t0 + u·Δt with u ~ U[0, 1) drawn per ray r when stratified, else t0."""
    t_s = t0
    if stratified != 0:
        state = wp.rand_init(seed, r)
        t_s = t0 + wp.randf(state) * dt
    return t_s


@wp.func
def reciprocal(v: wp.vec3) -> wp.vec3:
    """Componentwise 1/v, 0 where v = 0 (callers branch on the sign of v)."""
    r = wp.vec3(0.0)
    for a in range(3):
        if v[a] != 0.0:
            r[a] = 1.0 / v[a]
    return r


@wp.func
def grid_cell(p: wp.vec3, c: wp.vec3, h: wp.vec3, inv_h: wp.vec3, levels: int, res: int):
    """The cell holding p: (level, ijk, lower corner of the level's box c − h·2^level, 2^level),
    the level being the finest cascade containing p; ijk is clamped to the grid."""
    level = cascade_of(p, c, h, levels)
    scale = float(1 << level)
    lower = c - h * scale
    f = wp.cw_mul(p - lower, inv_h) * (0.5 * float(res) / scale)
    ijk = wp.vec3i(
        wp.clamp(int(wp.floor(f[0])), 0, res - 1),
        wp.clamp(int(wp.floor(f[1])), 0, res - 1),
        wp.clamp(int(wp.floor(f[2])), 0, res - 1),
    )
    return level, ijk, lower, scale


@wp.func
def cell_exit(o: wp.vec3, d: wp.vec3, inv_d: wp.vec3, lower: wp.vec3, size: wp.vec3) -> float:
    """Ray parameter at which o + t·d leaves the cell [lower, lower + size]."""
    t = _FAR
    for a in range(3):
        if d[a] > 0.0:
            t = wp.min(t, (lower[a] + size[a] - o[a]) * inv_d[a])
        elif d[a] < 0.0:
            t = wp.min(t, (lower[a] - o[a]) * inv_d[a])
    return t


@wp.func
def block_exit(o: wp.vec3, d: wp.vec3, inv_d: wp.vec3, lower: wp.vec3, cell_size: wp.vec3, corner: wp.vec3i,
               extent: wp.vec3) -> float:
    """Ray parameter at which o + t·d leaves the box of ``extent`` whose lower corner is that of
    cell ``corner`` of a level with lower corner ``lower`` and cells of ``cell_size``."""
    box_lo = lower + wp.cw_mul(wp.vec3(float(corner[0]), float(corner[1]), float(corner[2])), cell_size)
    return cell_exit(o, d, inv_d, box_lo, extent)


@wp.func
def first_step_past(t_leave: float, t_s: float, inv_dt: float) -> int:
    """Fixed steps t_k = t_s + k·Δt: the first k whose midpoint t_k + Δt/2 reaches t_leave,
    ⌈(t_leave − t_s)/Δt − 1/2⌉ (at most _MAX_ITERS)."""
    return int(wp.min(wp.ceil((t_leave - t_s) * inv_dt - 0.5), float(_MAX_ITERS)))


@wp.func
def empty_mip(mips: wp.array(dtype=wp.uint8), base: int, ijk: wp.vec3i, res: int, n_mips: int) -> int:
    """Largest m ≤ n_mips whose block (of 2^m cells per axis) holding the empty cell ijk is
    unmarked in every mip up to m (0 when the mip-1 block is marked); base = level·mip_cells."""
    m = int(0)
    searching = int(1)
    while m < n_mips and searching != 0:
        s = m + 1
        rm = res >> s
        if int(mips[base + ((ijk[0] >> s) * rm + (ijk[1] >> s)) * rm + (ijk[2] >> s)]) != 0:
            searching = 0
        else:
            base += rm * rm * rm
            m = s
    return m


@wp.func
def write_sample(
    j: int, r: int, o: wp.vec3, d: wp.vec3, t: float, t_end: float,
    ray_indices: wp.array(dtype=wp.int64),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    positions: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
):
    """Packed sample j: the interval [t, t_end] of ray r and its midpoint o + d (t + t_end) / 2."""
    ray_indices[j] = wp.int64(r)
    t_starts[j] = t
    t_ends[j] = t_end
    positions[j] = o + d * (0.5 * (t + t_end))
    directions[j] = d


@wp.func
def mark_step(mask: wp.uint64, bit: int) -> wp.uint64:
    """mask with ``bit`` set, or _REMARCH when the bit lies past 63."""
    if bit < 64:
        return mask | (wp.uint64(1) << wp.uint64(bit))
    return _REMARCH


@wp.func
def take_cell(
    k: int, k_stop: int, t: float, t_s: float, dt: float, t1: float, cone: float,
    n: int, cap: int, fill: int, masked: bool, mask: wp.uint64, k_first: int, base: int,
    r: int, o: wp.vec3, d: wp.vec3,
    ray_indices: wp.array(dtype=wp.int64),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    positions: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
):
    """Keep steps k .. k_stop − 1 (all in one occupied cell) while t < t1 and n < cap: the fill
    writes them as samples base + n onwards, the count with ``masked`` sets their bits
    k − k_first in ``mask``. Returns the next (k, t, n, mask)."""
    while k < k_stop and t < t1 and n < cap:
        t_end = wp.min(t + dt, t1)
        if fill != 0:
            write_sample(base + n, r, o, d, t, t_end, ray_indices, t_starts, t_ends, positions, directions)
        elif masked:
            mask = mark_step(mask, k - k_first)
        n += 1
        k += 1
        if cone > 0.0:
            t = t + dt
        else:
            t = t_s + float(k) * dt
    return k, t, n, mask


@wp.func
def skip_empty(k: int, t: float, t_s: float, dt: float, inv_dt: float, t1: float, t_leave: float,
               cfg: MarchConfig, iters: int):
    """Jump from the empty step k at t to the first step whose midpoint lies past t_leave (the
    exit of the empty block): fixed steps in one go, cone steps one at a time (counted in
    iters). Returns the next (k, t, iters)."""
    if cfg.cone > 0.0:
        t = t + dt
        while t < t1 and t + 0.5 * step_at(t, cfg.step, cfg.cone, cfg.max_step) < t_leave and iters < _MAX_ITERS:
            t = t + step_at(t, cfg.step, cfg.cone, cfg.max_step)
            iters += 1
    else:
        k = wp.max(k + 1, first_step_past(t_leave, t_s, inv_dt))
        t = t_s + float(k) * dt
    return k, t, iters


@wp.func
def replay_mask(
    mask: wp.uint64, k: int, t_s: float, step: float, t1: float, cap: int, base: int,
    r: int, o: wp.vec3, d: wp.vec3,
    ray_indices: wp.array(dtype=wp.int64),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    positions: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
) -> int:
    """Fill from the count's step mask: step k + b for each set bit b, at most cap samples from
    base on. Returns the samples written."""
    n = int(0)
    while mask != wp.uint64(0) and n < cap:
        if (mask & wp.uint64(1)) != wp.uint64(0):
            t = t_s + float(k) * step
            write_sample(base + n, r, o, d, t, wp.min(t + step, t1),
                         ray_indices, t_starts, t_ends, positions, directions)
            n += 1
        mask = mask >> wp.uint64(1)
        k += 1
    return n


@wp.func
def march_segment(
    k: int, k_end: int, t0: float, t1: float, cap: int, fill: int, masked: bool, base: int,
    r: int, o: wp.vec3, d: wp.vec3, c: wp.vec3, h: wp.vec3,
    bitfield: wp.array(dtype=wp.uint8),
    mips: wp.array(dtype=wp.uint8),
    cfg: MarchConfig,
    seed: int,
    ray_indices: wp.array(dtype=wp.int64),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    positions: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
):
    """March steps k .. k_end − 1 of ray r over [t0, t1] (see march_rays): keep the steps in
    occupied cells, jump over empty blocks. Returns (samples kept, step mask of the count)."""
    step = cfg.step
    cone = cfg.cone
    res = cfg.res
    dt = step_at(t0, step, cone, cfg.max_step)
    t_s = march_start(t0, dt, cfg.stratified, seed, r)
    t = t_s
    if k > 0:
        t = t_s + float(k) * dt
    inv_d = reciprocal(d)
    inv_h = reciprocal(h)
    inv_dt = 1.0 / step
    k_first = k
    n = int(0)
    mask = wp.uint64(0)
    iters = int(0)
    while t < t1 and k < k_end and n < cap and iters < _MAX_ITERS:
        iters += 1
        dt = step_at(t, step, cone, cfg.max_step)
        t_end = wp.min(t + dt, t1)
        level, ijk, lower, scale = grid_cell(o + d * (0.5 * (t + t_end)), c, h, inv_h, cfg.levels, res)
        if is_occupied(bitfield, cell_id(level, ijk, res)):
            # fixed steps: every step whose midpoint lies before the cell's exit is in the cell
            k_stop = k + 1
            if cone == 0.0:
                size = h * (2.0 * scale / float(res))
                t_leave = block_exit(o, d, inv_d, lower, size, ijk, size)
                k_stop = wp.min(wp.max(k + 1, first_step_past(t_leave, t_s, inv_dt)), k_end)
            k, t, n, mask = take_cell(k, k_stop, t, t_s, dt, t1, cone, n, cap, fill, masked, mask, k_first, base,
                                      r, o, d, ray_indices, t_starts, t_ends, positions, directions)
        else:
            mip = empty_mip(mips, level * cfg.mip_cells, ijk, res, cfg.n_mips)
            size = h * (2.0 * scale / float(res))
            block = wp.vec3i((ijk[0] >> mip) << mip, (ijk[1] >> mip) << mip, (ijk[2] >> mip) << mip)
            t_leave = block_exit(o, d, inv_d, lower, size, block, size * float(1 << mip))
            k, t, iters = skip_empty(k, t, t_s, dt, inv_dt, t1, t_leave, cfg, iters)
    return n, mask


# Per ray: [t0, t1] = [max(near, t_enter), min(far, t_exit)] of the outermost cascade box.
# Fixed step: t_k = t_s + k·Δt, t_s = t0 + u·Δt (u ~ U[0,1) when stratified, else 0).
# Cone: t_{k+1} = t_k + clamp(t_k·cone, step, max_step).
# Sample k is the interval [t_k, min(t_k + Δt, t1)], kept when its midpoint's cell (finest
# cascade containing it) is occupied. With fixed steps, the samples whose midpoints lie before
# that cell's exit are kept with it (one cell lookup per cell). From an empty cell the march
# jumps (DDA) to the first t_k whose midpoint lies past the exit of the largest empty mip block
# holding the cell (the cell itself when its mip-1 block is marked). At most max_per_ray samples
# per ray.
# Item i marches segment j = i mod n_seg of ray r = i div n_seg: steps k in [j·seg_steps,
# (j+1)·seg_steps), the last segment to the ray's end (n_seg = 1 with cone steps). Since t_k
# depends on k alone, a segment's march joins the whole ray's march at its first occupied cell.
# fill = 0: seg_counts[i] = samples of the segment (at most max_per_ray); seg_offsets[0] = 0.
# Between the passes seg_offsets[1:] becomes the inclusive prefix sum of the (capped) counts.
# fill = 1: the segment's first seg_offsets[i+1] − seg_offsets[i] samples go to seg_offsets[i]
# onwards, and ray_offsets[r] = seg_offsets[r·n_seg] (ray_offsets[n_rays] = seg_offsets[-1]).
# Step masks (fixed steps, when the host passes step_masks): the count pass also stores bit
# k − j·seg_steps of step_masks[i] for every kept step k, and the fill pass writes the samples
# from those bits instead of marching again; a segment with a kept step past bit 63 stores
# _REMARCH and is marched again (the last segment of a ray longer than planned).
# At most 64 registers: twice the resident threads of the unconstrained build (96), so more rays'
# cell lookups are in flight at once.
@wp.kernel(cuda_max_registers=64)
def march_rays(
    first: int,
    fill: int,
    rays_o: wp.array(dtype=wp.vec3),
    rays_d: wp.array(dtype=wp.vec3),
    aabb: wp.array(dtype=float),
    bitfield: wp.array(dtype=wp.uint8),
    mips: wp.array(dtype=wp.uint8),
    cfg: MarchConfig,
    seed: int,
    seg_counts: wp.array(dtype=wp.int32),
    seg_offsets: wp.array(dtype=wp.int32),
    ray_offsets: wp.array(dtype=wp.int32),
    ray_indices: wp.array(dtype=wp.int64),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    positions: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    step_masks: wp.array(dtype=wp.uint64),
):
    n_seg = cfg.n_seg
    i = first + wp.tid()
    r = i // n_seg
    seg = i - r * n_seg
    o = rays_o[r]
    d = rays_d[r]
    c = box_center(aabb)
    h = box_half(aabb)
    span = ray_span(o, d, c, h, cfg)
    t0 = span[0]
    t1 = span[1]

    k = seg * cfg.seg_steps
    k_end = k + cfg.seg_steps
    if seg == n_seg - 1:
        k_end = _MAX_ITERS
    base = int(0)
    cap = cfg.max_per_ray
    if fill != 0:
        base = int(seg_offsets[i])
        cap = int(seg_offsets[i + 1]) - base
        if seg == 0:
            ray_offsets[r] = base
        if i == rays_o.shape[0] * n_seg - 1:
            ray_offsets[r + 1] = int(seg_offsets[i + 1])

    n = int(0)
    mask = wp.uint64(0)
    masked = step_masks.shape[0] > 0
    if masked and fill != 0:
        mask = step_masks[i]
    live = t0 < t1 and wp.dot(d, d) > 0.0 and cap > 0
    if live and masked and fill != 0 and mask != _REMARCH:
        t_s = march_start(t0, cfg.step, cfg.stratified, seed, r)
        n = replay_mask(mask, k, t_s, cfg.step, t1, cap, base, r, o, d,
                        ray_indices, t_starts, t_ends, positions, directions)
    elif live:
        n, mask = march_segment(k, k_end, t0, t1, cap, fill, masked, base, r, o, d, c, h, bitfield, mips, cfg, seed,
                                ray_indices, t_starts, t_ends, positions, directions)
    if fill == 0:
        seg_counts[i] = n
        if masked:
            step_masks[i] = mask
        if i == 0:
            seg_offsets[0] = 0
