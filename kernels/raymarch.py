"""Ray marching through an occupancy grid, run twice: count, then fill.

A ray's steps t_k have a closed form in k (fixed, or cone steps: :class:`StepSchedule`), so its
steps are split into segments of ``seg_steps`` steps, each marched by its own thread (the last
one runs to the ray's end); with a scene contraction one thread marches a ray. The kernel is
built from the helpers of :mod:`ngp_warp.kernels.raymarch_funcs` (the ray's interval, the
steps, the cell lookup) and the walks below: through an occupied cell (:func:`take_cell`) and
over empty space (:func:`march_segment`), and through contracted space
(:func:`march_contracted`). After a large launch's fill, :func:`sample_points` writes the
samples' positions and directions, one thread per sample.
Sampling carries no gradient, so there is no backward kernel here.
"""

import warp as wp

from ngp_warp.kernels.occupancy import box_center, box_half, cell_id, is_occupied
from ngp_warp.kernels.raymarch_funcs import (_MAX_ITERS, _REMARCH, NO_CONTRACTION, MarchConfig, StepSchedule, block_exit,
                                             contracted_point, contracted_step_at, empty_mip, first_step_past,
                                             grid_cell, march_start, mark_step, midpoint, ray_span, ray_steps,
                                             reciprocal, step_start, store_mask, write_sample)

wp.set_module_options({"enable_backward": False})


@wp.func
def take_cell(
    k: int, k_stop: int, t: float, steps: StepSchedule, t1: float,
    n: int, cap: int, fill: int, words: int, mask: wp.uint64, word: int, k_first: int, base: int,
    r: int, o: wp.vec3, d: wp.vec3,
    ray_indices: wp.array(dtype=wp.int64),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    positions: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    step_masks: wp.array(dtype=wp.uint64),
    slot: int,
):
    """Keep steps k .. k_stop − 1 (all in one occupied cell; t = t_k) while t < t1 and n < cap:
    the fill writes them as samples base + n onwards, the count with step masks (``words`` > 0)
    sets their bits k − k_first in the segment's mask at ``slot`` (mark_step). Returns the next
    (k, t, n, mask, word)."""
    while k < k_stop and t < t1 and n < cap:
        t_next = step_start(steps, k + 1)
        if fill != 0:
            write_sample(base + n, r, o, d, t, wp.min(t_next, t1), ray_indices, t_starts, t_ends, positions, directions)
        elif words > 0:
            mask, word = mark_step(step_masks, slot, words, mask, word, k - k_first)
        n += 1
        k += 1
        t = t_next
    return k, t, n, mask, word


@wp.func
def replay_mask(
    step_masks: wp.array(dtype=wp.uint64), slot: int, words: int, k: int, steps: StepSchedule, t1: float,
    cap: int, base: int, r: int, o: wp.vec3, d: wp.vec3,
    ray_indices: wp.array(dtype=wp.int64),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    positions: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
) -> int:
    """Fill from the count's step mask (``words`` words from step_masks[slot] on): step k + b
    for each set bit b, at most cap samples from base on. Returns the samples written."""
    n = int(0)
    for w in range(words):
        mask = step_masks[slot + w]
        kw = k + 64 * w
        while mask != wp.uint64(0) and n < cap:
            if (mask & wp.uint64(1)) != wp.uint64(0):
                write_sample(base + n, r, o, d, step_start(steps, kw), wp.min(step_start(steps, kw + 1), t1),
                             ray_indices, t_starts, t_ends, positions, directions)
                n += 1
            mask = mask >> wp.uint64(1)
            kw += 1
    return n


@wp.func
def march_segment(
    k: int, k_end: int, steps: StepSchedule, t1: float, cap: int, fill: int, words: int, base: int,
    r: int, o: wp.vec3, d: wp.vec3, c: wp.vec3, h: wp.vec3,
    bitfield: wp.array(dtype=wp.uint8),
    mips: wp.array(dtype=wp.uint8),
    cfg: MarchConfig,
    ray_indices: wp.array(dtype=wp.int64),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    positions: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    step_masks: wp.array(dtype=wp.uint64),
    slot: int,
):
    """March steps k .. k_end − 1 of ray r up to t1 (see march_rays): keep the steps in
    occupied cells, jump over empty blocks. Returns the samples kept; the count with step masks
    (``words`` > 0) stores the segment's mask at ``slot``."""
    res = cfg.res
    t = step_start(steps, k)
    inv_d = reciprocal(d)
    inv_h = reciprocal(h)
    k_first = k
    n = int(0)
    mask = wp.uint64(0)
    word = int(0)
    iters = int(0)
    while t < t1 and k < k_end and n < cap and iters < _MAX_ITERS:
        iters += 1
        t_end = wp.min(step_start(steps, k + 1), t1)
        level, ijk, lower, scale = grid_cell(midpoint(o, d, t, t_end), c, h, inv_h, cfg.levels, res)
        size = h * (2.0 * scale / float(res))
        if is_occupied(bitfield, cell_id(level, ijk, res)):
            # every step whose midpoint lies before the cell's exit is in the cell
            t_leave = block_exit(o, d, inv_d, lower, size, ijk, size)
            k_stop = wp.min(wp.max(k + 1, first_step_past(steps, t_leave)), k_end)
            k, t, n, mask, word = take_cell(k, k_stop, t, steps, t1, n, cap, fill, words, mask, word, k_first, base,
                                            r, o, d, ray_indices, t_starts, t_ends, positions, directions,
                                            step_masks, slot)
        else:
            mip = empty_mip(mips, level * cfg.mip_cells, ijk, res, cfg.n_mips)
            block = wp.vec3i((ijk[0] >> mip) << mip, (ijk[1] >> mip) << mip, (ijk[2] >> mip) << mip)
            t_leave = block_exit(o, d, inv_d, lower, size, block, size * float(1 << mip))
            k = wp.max(k + 1, first_step_past(steps, t_leave))
            t = step_start(steps, k)
    if fill == 0 and words > 0:
        store_mask(step_masks, slot, words, mask, word)
    return n


@wp.func
def march_contracted(
    t0: float, t1: float, cap: int, fill: int, base: int, r: int, o: wp.vec3, d: wp.vec3,
    c: wp.vec3, h: wp.vec3,
    bitfield: wp.array(dtype=wp.uint8),
    cfg: MarchConfig,
    seed: int,
    ray_indices: wp.array(dtype=wp.int64),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    positions: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
) -> int:
    """March ray r over [t0, t1] in world space with contracted steps (contracted_step_at), one
    cell lookup per step at the contracted midpoint; keep the steps in occupied cells. Returns
    the samples kept (written from base on by the fill)."""
    v = wp.cw_div(d, cfg.inner_h)
    inv_h = reciprocal(h)
    t = march_start(t0, contracted_step_at(o + d * t0, v, t0, cfg), cfg.stratified, seed, r)
    n = int(0)
    iters = int(0)
    while t < t1 and n < cap and iters < _MAX_ITERS:
        iters += 1
        dt = contracted_step_at(o + d * t, v, t, cfg)
        t_end = wp.min(t + dt, t1)
        y = contracted_point(midpoint(o, d, t, t_end), cfg)
        level, ijk, lower, scale = grid_cell(y, c, h, inv_h, cfg.levels, cfg.res)
        if is_occupied(bitfield, cell_id(level, ijk, cfg.res)):
            if fill != 0:
                write_sample(base + n, r, o, d, t, t_end, ray_indices, t_starts, t_ends, positions, directions)
            n += 1
        if t + dt > t:
            t = t + dt
        else:  # a step float32 cannot add: the ray ends
            t = t1
    return n


# Per ray: [t0, t1] = [max(near, t_enter), min(far, t_exit)] of the outermost cascade box.
# Fixed step: t_k = t_s + k·Δt, t_s = t0 + u·Δt (u ~ U[0,1) when stratified, else 0).
# Cone: t_{k+1} = t_k + clamp(t_k·cone, step, max_step), in closed form (ray_steps):
#   t_k = t_s + k·step (k < k_cone), t_cone·(1 + cone)^(k − k_cone) (k < k_max),
#   t_max + (k − k_max)·max_step.
# Sample k is the interval [t_k, min(t_{k+1}, t1)], kept when its midpoint's cell (finest
# cascade containing it) is occupied; the samples whose midpoints lie before that cell's exit
# are kept with it (one cell lookup per cell). From an empty cell the march jumps (DDA) to the
# first t_k whose midpoint lies past the exit of the largest empty mip block holding the cell
# (the cell itself when its mip-1 block is marked). At most max_per_ray samples per ray.
# Item i marches segment j = i mod n_seg of ray r = i div n_seg: steps k in [j·seg_steps,
# (j+1)·seg_steps), the last segment to the ray's end. Since t_k depends on k alone, a
# segment's march joins the whole ray's march at its first occupied cell.
# fill = 0: seg_counts[i] = samples of the segment (at most max_per_ray); seg_offsets[0] = 0.
# Between the passes seg_offsets[1:] becomes the inclusive prefix sum of the (capped) counts.
# fill = 1: the segment's first seg_offsets[i+1] − seg_offsets[i] samples go to seg_offsets[i]
# onwards, and ray_offsets[r] = seg_offsets[r·n_seg] (ray_offsets[n_rays] = seg_offsets[-1]).
# Step masks (when the host passes step_masks, W = len(step_masks) / items words per segment,
# W·64 ≥ seg_steps): the count pass also sets bit b = k − j·seg_steps of segment i's mask
# (word step_masks[i·W + b div 64], bit b mod 64) for every kept step k, and the fill pass writes
# the samples from those bits instead of marching again; a segment with a kept step past bit
# W·64 − 1 stores _REMARCH in its first word and is marched again (the last segment of a ray
# longer than planned).
# Contraction (cfg.contraction ≥ 0): the grid box (c, h) lives in contracted space and one thread
# marches a ray over [near, far]: t_{k+1} = t_k + max(Δy / ‖J_C(x_k)(d ⊘ h_in)‖, min(t_k·cone,
# max_step)), x_k = (o + t_k·d − c_in) ⊘ h_in, Δy = cfg.step; sample k is kept when the cell of
# C(x) at its midpoint is occupied (no DDA: cells are not boxes in world space).
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
    words = step_masks.shape[0] // (rays_o.shape[0] * n_seg)
    slot = i * words
    replay = words > 0 and fill != 0
    if replay:
        replay = step_masks[slot] != _REMARCH
    live = t0 < t1 and wp.dot(d, d) > 0.0 and cap > 0
    if live and cfg.contraction != NO_CONTRACTION:
        n = march_contracted(t0, t1, cap, fill, base, r, o, d, c, h, bitfield, cfg, seed,
                             ray_indices, t_starts, t_ends, positions, directions)
    elif live and replay:
        n = replay_mask(step_masks, slot, words, k, ray_steps(t0, cfg, seed, r), t1, cap, base, r, o, d,
                        ray_indices, t_starts, t_ends, positions, directions)
    elif live:
        n = march_segment(k, k_end, ray_steps(t0, cfg, seed, r), t1, cap, fill, words, base, r, o, d, c, h,
                          bitfield, mips, cfg, ray_indices, t_starts, t_ends, positions, directions,
                          step_masks, slot)
    elif fill == 0 and words > 0:
        store_mask(step_masks, slot, words, wp.uint64(0), 0)
    if fill == 0:
        seg_counts[i] = n
        if i == 0:
            seg_offsets[0] = 0


# Sample j of ray r = ray_indices[j] < N (the rays' count; padding rows name ray N):
#   positions[j] = o_r + d_r (t_starts[j] + t_ends[j]) / 2,  directions[j] = d_r
# One thread per sample, so that neighbouring threads write neighbouring rows: the fill pass of a
# large launch leaves these to it (its threads write a segment's samples one after another).
@wp.kernel
def sample_points(
    first: int,
    rays_o: wp.array(dtype=wp.vec3),
    rays_d: wp.array(dtype=wp.vec3),
    ray_indices: wp.array(dtype=wp.int64),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    positions: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
):
    j = first + wp.tid()
    r = int(ray_indices[j])
    if r < rays_o.shape[0]:
        d = rays_d[r]
        positions[j] = midpoint(rays_o[r], d, t_starts[j], t_ends[j])
        directions[j] = d
