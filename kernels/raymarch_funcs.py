"""The march's building blocks (see :mod:`ngp_warp.kernels.raymarch`): its settings, the ray's
interval (:func:`ray_span`), the step size (:func:`step_at`, :func:`contracted_step_at`), the
cell lookup (:func:`grid_cell`), the steps in closed form (:class:`StepSchedule`), the DDA exits
of cells and empty blocks, and the sample writer.

With a scene contraction (``MarchConfig.contraction`` ≥ 0) the march runs in world space but
the grid lives in contracted space: a world point p is normalised by the inner box,
x = (p − c_in) ⊘ h_in, and looked up at y = C(x) (:mod:`ngp_warp.kernels.contraction`).
"""

import warp as wp

from ngp_warp.kernels.contraction import contract, contracted_speed
from ngp_warp.kernels.occupancy import cascade_of

wp.set_module_options({"enable_backward": False})

_FAR = wp.constant(1.0e30)
# Loop iterations per ray never exceed this (ends degenerate rays, e.g. near-zero directions
# whose t range float32 steps cannot resolve); sane rays need far fewer (~1024·2^levels).
_MAX_ITERS = wp.constant(1 << 24)
# A step mask whose first word has every bit set means "march again" (see march_rays).
_REMARCH = wp.constant(wp.uint64(0xFFFFFFFFFFFFFFFF))
NO_CONTRACTION = wp.constant(-1)  # MarchConfig.contraction without a contraction; else kernels.contraction's L2 / LINF


@wp.struct
class MarchConfig:
    """The march's settings: grid (res, levels, n_mips, mip_cells), ray interval and steps, the
    per-ray cap, stratification, the segments per ray, and the scene contraction (its kind, or
    NO_CONTRACTION, and the inner box's centre and half extents) (one value per batch, so the
    host builds it once per configuration)."""

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
    contraction: int
    inner_c: wp.vec3
    inner_h: wp.vec3


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
    box c ± h·2^(levels−1); t0 ≥ t1 when the ray misses it. With a contraction the grid covers
    all of space: [near, far]."""
    if cfg.contraction != NO_CONTRACTION:
        return wp.vec2(cfg.near, cfg.far)
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
def contracted_point(p: wp.vec3, cfg: MarchConfig) -> wp.vec3:
    """y = C((p − c_in) ⊘ h_in): the grid coordinates of world point p under the contraction."""
    return contract(wp.cw_div(p - cfg.inner_c, cfg.inner_h), cfg.contraction)


@wp.func
def contracted_step_at(p: wp.vec3, v: wp.vec3, t: float, cfg: MarchConfig) -> float:
    """Δt = max(Δy / ‖J_C(x) v‖, min(t·cone, max_step)) at world point p = o + t·d, v = d ⊘ h_in:
    the world step spanning the contracted step Δy = cfg.step, or the cone step if longer."""
    x = wp.cw_div(p - cfg.inner_c, cfg.inner_h)
    dt = cfg.step / contracted_speed(x, v, cfg.contraction)
    if cfg.cone > 0.0:
        dt = wp.max(dt, wp.min(t * cfg.cone, cfg.max_step))
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


@wp.struct
class StepSchedule:
    """One ray's steps in closed form, t_k for any k (see :func:`step_start`): fixed steps up to
    k_cone, then growing by the factor 1 + cone up to k_max, then fixed steps of max_step
    (k_cone = k_max = _MAX_ITERS without a cone)."""

    t_s: float
    step: float
    growth: float
    max_step: float
    k_cone: int
    t_cone: float
    k_max: int
    t_max: float


@wp.func
def ray_steps(t0: float, cfg: MarchConfig, seed: int, r: int) -> StepSchedule:
    """Ray r's step schedule from t0 (jittered by march_start). With a cone, step k is fixed
    while t_k·cone ≤ step (k < k_cone), t_k·cone while below max_step (k < k_max), else
    max_step: the recurrence t_{k+1} = t_k + clip(t_k·cone, step, max_step) in closed form."""
    sched = StepSchedule()
    sched.step = cfg.step
    sched.max_step = cfg.max_step
    sched.t_s = march_start(t0, step_at(t0, cfg.step, cfg.cone, cfg.max_step), cfg.stratified, seed, r)
    sched.k_cone = _MAX_ITERS
    sched.k_max = _MAX_ITERS
    if cfg.cone > 0.0:
        sched.growth = wp.log(1.0 + cfg.cone)
        t_fixed = cfg.step / cfg.cone  # the cone step reaches the fixed step here
        k_cone = int(0)
        if sched.t_s <= t_fixed:
            k_cone = int(wp.min(wp.floor((t_fixed - sched.t_s) / cfg.step) + 1.0, float(_MAX_ITERS)))
        sched.k_cone = k_cone
        sched.t_cone = sched.t_s + float(k_cone) * cfg.step
        t_capped = cfg.max_step / cfg.cone  # the cone step reaches max_step here
        growing = float(0.0)
        if sched.t_cone < t_capped:
            growing = wp.ceil(wp.log(t_capped / sched.t_cone) / sched.growth)
        sched.k_max = k_cone + int(wp.min(growing, float(_MAX_ITERS - k_cone)))
        sched.t_max = sched.t_cone * wp.exp(float(sched.k_max - k_cone) * sched.growth)
    return sched


@wp.func
def step_start(s: StepSchedule, k: int) -> float:
    """t_k: t_s + k·step, then t_cone·(1 + cone)^(k − k_cone), then t_max + (k − k_max)·max_step."""
    if k < s.k_cone:
        return s.t_s + float(k) * s.step
    if k < s.k_max:
        return s.t_cone * wp.exp(float(k - s.k_cone) * s.growth)
    return s.t_max + float(k - s.k_max) * s.max_step


@wp.func
def step_mid(s: StepSchedule, k: int) -> float:
    """The midpoint (t_k + t_{k+1}) / 2 of step k."""
    return 0.5 * (step_start(s, k) + step_start(s, k + 1))


@wp.func
def first_step_past(s: StepSchedule, t_leave: float) -> int:
    """The first k whose midpoint reaches t_leave (at most _MAX_ITERS): among the fixed first
    steps ⌈(t_leave − t_s)/step − 1/2⌉; past them the log of the growth or the max_step
    count, corrected by one either way against :func:`step_mid` (float rounding)."""
    k = int(wp.min(wp.ceil((t_leave - s.t_s) / s.step - 0.5), float(_MAX_ITERS)))
    if k < s.k_cone:
        return k
    if s.k_max > s.k_cone and t_leave <= step_mid(s, s.k_max - 1):
        ratio = t_leave / (s.t_cone * 0.5 * (1.0 + wp.exp(s.growth)))
        k = s.k_cone + wp.max(int(wp.ceil(wp.log(wp.max(ratio, 1.0e-30)) / s.growth)), 0)
        k = wp.min(k, s.k_max - 1)
    else:
        k = s.k_max + wp.max(int(wp.min(wp.ceil((t_leave - s.t_max) / s.max_step - 0.5), float(_MAX_ITERS))), 0)
    if k > s.k_cone and step_mid(s, k - 1) >= t_leave:
        k -= 1
    elif step_mid(s, k) < t_leave:
        k += 1
    return k


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
def midpoint(o: wp.vec3, d: wp.vec3, t: float, t_end: float) -> wp.vec3:
    """o + d (t + t_end) / 2: the point a step's cell is looked up at, and its sample's position."""
    return o + d * (0.5 * (t + t_end))


@wp.func
def write_sample(
    j: int, r: int, o: wp.vec3, d: wp.vec3, t: float, t_end: float,
    ray_indices: wp.array(dtype=wp.int64),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    positions: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
):
    """Packed sample j: the interval [t, t_end] of ray r, and its midpoint o + d (t + t_end) / 2
    and direction unless ``positions`` is empty (the pass ``sample_points`` writes them)."""
    ray_indices[j] = wp.int64(r)
    t_starts[j] = t
    t_ends[j] = t_end
    if positions.shape[0] > 0:
        positions[j] = midpoint(o, d, t, t_end)
        directions[j] = d


@wp.func
def mark_step(step_masks: wp.array(dtype=wp.uint64), slot: int, words: int, mask: wp.uint64, word: int,
              bit: int):
    """Set ``bit`` of a segment's step mask: ``words`` words from step_masks[slot] on, of which
    ``mask`` is word ``word`` (held in a register; the words before it are stored, zero where
    no step was kept). A bit past the last word sets word = ``words`` (march again). Returns
    (mask, word)."""
    w = bit >> 6
    if word >= words or w >= words:
        return mask, words
    while word < w:
        step_masks[slot + word] = mask
        mask = wp.uint64(0)
        word += 1
    return mask | (wp.uint64(1) << wp.uint64(bit - 64 * w)), word


@wp.func
def store_mask(step_masks: wp.array(dtype=wp.uint64), slot: int, words: int, mask: wp.uint64, word: int):
    """The count's last stores of a segment's step mask (see mark_step): word ``word`` and
    zeros after it, or _REMARCH in its first word when a kept step lay past its last word."""
    if word >= words:
        step_masks[slot] = _REMARCH
    else:
        step_masks[slot + word] = mask
        for w in range(word + 1, words):
            step_masks[slot + w] = wp.uint64(0)
