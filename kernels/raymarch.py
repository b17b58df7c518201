"""Ray marching through an occupancy grid (one thread per ray), run twice: count, then fill.

Sampling carries no gradient, so there is no backward kernel here.
"""

import warp as wp

from ngp_warp.kernels.occupancy import box_center, box_half, cascade_of, cell_id, is_occupied

wp.set_module_options({"enable_backward": False})

_FAR = wp.constant(1.0e30)
# Loop iterations per ray never exceed this (ends degenerate rays, e.g. near-zero directions
# whose t range float32 steps cannot resolve); sane rays need far fewer (~1024·2^levels).
_MAX_ITERS = wp.constant(1 << 24)


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
def reciprocal(v: wp.vec3) -> wp.vec3:
    """Componentwise 1/v, 0 where v = 0 (callers branch on the sign of v)."""
    r = wp.vec3(0.0)
    for a in range(3):
        if v[a] != 0.0:
            r[a] = 1.0 / v[a]
    return r


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
def step_at(t: float, step: float, cone: float, max_step: float) -> float:
    """Δt = step (cone = 0) or clamp(t·cone, step, max_step)."""
    dt = step
    if cone > 0.0:
        dt = wp.clamp(t * cone, step, max_step)
    return dt


# Per ray: [t0, t1] = [max(near, t_enter), min(far, t_exit)] of the outermost cascade box.
# Fixed step: t_k = t_s + k·Δt, t_s = t0 + u·Δt (u ~ U[0,1) when stratified, else 0).
# Cone: t_{k+1} = t_k + clamp(t_k·cone, step, max_step).
# Sample k is the interval [t_k, min(t_k + Δt, t1)], kept when its midpoint's cell (finest
# cascade containing it) is occupied. From an empty cell the march jumps (DDA) to the first
# t_k whose midpoint lies past the cell's exit. At most max_per_ray samples per ray.
# fill = 0: counts[r] = number of samples. fill = 1: write them at offsets[r] .. offsets[r+1].
@wp.kernel
def march_rays(
    first: int,
    fill: int,
    rays_o: wp.array(dtype=wp.vec3),
    rays_d: wp.array(dtype=wp.vec3),
    aabb: wp.array(dtype=float),
    bitfield: wp.array(dtype=wp.uint8),
    res: int,
    levels: int,
    near: float,
    far: float,
    step: float,
    cone: float,
    max_step: float,
    max_per_ray: int,
    stratified: int,
    seed: int,
    counts: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32),
    ray_indices: wp.array(dtype=wp.int64),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    positions: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
):
    r = first + wp.tid()
    o = rays_o[r]
    d = rays_d[r]
    c = box_center(aabb)
    h = box_half(aabb)
    outer = h * float(1 << (levels - 1))
    hit = ray_box(o, d, c - outer, c + outer)
    t0 = wp.max(hit[0], near)
    t1 = wp.min(hit[1], far)

    base = int(0)
    cap = max_per_ray
    if fill != 0:
        base = int(offsets[r])
        cap = wp.min(cap, int(offsets[r + 1]) - base)

    n = int(0)
    if t0 < t1 and wp.dot(d, d) > 0.0:
        state = wp.rand_init(seed, r)
        dt = step_at(t0, step, cone, max_step)
        t_s = t0
        if stratified != 0:
            t_s = t0 + wp.randf(state) * dt
        t = t_s
        k = int(0)
        inv_d = reciprocal(d)
        inv_h = reciprocal(h)
        inv_dt = 1.0 / step
        iters = int(0)
        while t < t1 and n < cap and iters < _MAX_ITERS:
            iters += 1
            dt = step_at(t, step, cone, max_step)
            t_end = wp.min(t + dt, t1)
            p = o + d * (0.5 * (t + t_end))
            level = cascade_of(p, c, h, levels)
            scale = float(1 << level)
            lower = c - h * scale
            f = wp.cw_mul(p - lower, inv_h) * (0.5 * float(res) / scale)
            ijk = wp.vec3i(
                wp.clamp(int(wp.floor(f[0])), 0, res - 1),
                wp.clamp(int(wp.floor(f[1])), 0, res - 1),
                wp.clamp(int(wp.floor(f[2])), 0, res - 1),
            )
            if is_occupied(bitfield, cell_id(level, ijk, res)):
                if fill != 0:
                    j = base + n
                    ray_indices[j] = wp.int64(r)
                    t_starts[j] = t
                    t_ends[j] = t_end
                    positions[j] = p
                    directions[j] = d
                n += 1
                k += 1
                if cone > 0.0:
                    t = t + dt
                else:
                    t = t_s + float(k) * dt
            else:
                size = h * (2.0 * scale / float(res))
                cell_lo = lower + wp.cw_mul(wp.vec3(float(ijk[0]), float(ijk[1]), float(ijk[2])), size)
                t_leave = cell_exit(o, d, inv_d, cell_lo, size)
                if cone > 0.0:
                    t = t + dt
                    while t < t1 and t + 0.5 * step_at(t, step, cone, max_step) < t_leave and iters < _MAX_ITERS:
                        t = t + step_at(t, step, cone, max_step)
                        iters += 1
                else:
                    target = wp.min(wp.ceil((t_leave - t_s) * inv_dt - 0.5), float(_MAX_ITERS))
                    k = wp.max(k + 1, int(target))
                    t = t_s + float(k) * dt
    if fill == 0:
        counts[r] = n
