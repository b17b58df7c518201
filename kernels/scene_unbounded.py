"""The unbounded 360° procedural scene: the demo scene's objects on a ground plane to the horizon.

* the four textured objects of ``kernels/scene.py`` (sphere-traced and shaded by its funcs),
* an infinite ground plane z = GROUND_Z under them (the torus rests on it) with a checker whose
  contrast fades with the distance r from the centre, c = mean + (checker - mean) / (1 + (r/F)^2),
  so the texture stays well defined out to the horizon,
* a ring of PILLAR_COUNT tall cylinders at distance PILLAR_RING, each its own hue, banded,
* a distant environment at infinity (a function of the direction only): mountains below a
  skyline elevation s(phi) = base + sum_i a_i sin(f_i phi + p_i), a sky gradient above.

Ground and pillars are Lambertian under the demo scene's light: albedo (ambient + diffuse
max(n.l, 0)); the objects keep their Blinn-Phong highlight. Every ray has a colour (no alpha).
Not differentiable: there is no backward kernel. The plain-Python constants are shared with the
float64 twin in ``ngp_warp/_reference/scene_unbounded.py``.
"""

import math

import warp as wp

from ngp_warp.kernels.scene import AMBIENT, DIFFUSE, LIGHT_DIR, parity, shade, trace, view_direction, view_pixel

wp.set_module_options({"enable_backward": False})

# ---- scene description (plain Python; the kernel uses the wp.constant copies) -------------
GROUND_Z = -0.47
GROUND_CELL = 0.5  # checker cell size, world units
GROUND_A = (0.36, 0.52, 0.24)
GROUND_B = (0.80, 0.74, 0.55)
GROUND_FADE = 6.0  # F: the checker's contrast halves at r = F
PILLAR_COUNT = 8
PILLAR_RING = 20.0  # distance of the pillars' axes from the centre
PILLAR_PHASE = 0.3  # azimuth of pillar 0, radians
PILLAR_RADIUS = 1.0
PILLAR_HEIGHT = 4.0  # above the ground
PILLAR_BAND = 0.8  # height of the pale bands
PILLAR_PALE = (0.92, 0.92, 0.88)
SKYLINE_BASE = 0.07  # radians of elevation
SKYLINE_WAVES = ((0.035, 3.0, 0.4), (0.02, 7.0, 1.9), (0.01, 13.0, 0.7))  # amplitude, frequency, phase
MOUNTAIN_LOW = (0.30, 0.33, 0.40)
MOUNTAIN_HIGH = (0.62, 0.64, 0.70)
SKY_HORIZON = (0.85, 0.88, 0.92)
SKY_ZENITH = (0.30, 0.50, 0.85)

# ---- Warp copies ----------------------------------------------------------------------------
_GROUND_Z = wp.constant(GROUND_Z)
_GROUND_CELL = wp.constant(GROUND_CELL)
_GROUND_A = wp.constant(wp.vec3(*GROUND_A))
_GROUND_B = wp.constant(wp.vec3(*GROUND_B))
_GROUND_FADE = wp.constant(GROUND_FADE)
_PILLAR_COUNT = wp.constant(PILLAR_COUNT)
_PILLAR_RING = wp.constant(PILLAR_RING)
_PILLAR_PHASE = wp.constant(PILLAR_PHASE)
_PILLAR_R = wp.constant(PILLAR_RADIUS)
_PILLAR_TOP = wp.constant(GROUND_Z + PILLAR_HEIGHT)
_PILLAR_BAND = wp.constant(PILLAR_BAND)
_PILLAR_PALE = wp.constant(wp.vec3(*PILLAR_PALE))
_SKYLINE_BASE = wp.constant(SKYLINE_BASE)
_WAVE_A = wp.constant(wp.vec3(*(w[0] for w in SKYLINE_WAVES)))
_WAVE_F = wp.constant(wp.vec3(*(w[1] for w in SKYLINE_WAVES)))
_WAVE_P = wp.constant(wp.vec3(*(w[2] for w in SKYLINE_WAVES)))
_MOUNTAIN_LOW = wp.constant(wp.vec3(*MOUNTAIN_LOW))
_MOUNTAIN_HIGH = wp.constant(wp.vec3(*MOUNTAIN_HIGH))
_SKY_HORIZON = wp.constant(wp.vec3(*SKY_HORIZON))
_SKY_ZENITH = wp.constant(wp.vec3(*SKY_ZENITH))
_LIGHT = wp.constant(wp.vec3(*LIGHT_DIR))
_AMBIENT = wp.constant(AMBIENT)
_DIFFUSE = wp.constant(DIFFUSE)
_TWO_PI = wp.constant(2.0 * math.pi)

MISS = -1.0  # t of a ray that reaches the environment
HIT_SKY, HIT_OBJECT, HIT_GROUND, HIT_PILLAR = 0, 1, 2, 3  # what a ray hits first
_MISS = wp.constant(MISS)
_HIT_SKY = wp.constant(HIT_SKY)
_HIT_OBJECT = wp.constant(HIT_OBJECT)
_HIT_GROUND = wp.constant(HIT_GROUND)
_HIT_PILLAR = wp.constant(HIT_PILLAR)


@wp.func
def pillar_center(k: int) -> wp.vec2:
    phi = _PILLAR_PHASE + _TWO_PI * float(k) / float(_PILLAR_COUNT)
    return wp.vec2(_PILLAR_RING * wp.cos(phi), _PILLAR_RING * wp.sin(phi))


# One pillar: |(o + t d)_xy - c|^2 = R^2 for the side (smaller root, z in [GROUND_Z, top]),
# t = (top - o_z) / d_z for the cap (|xy - c| <= R). Rays start outside every pillar.
@wp.func
def pillar_hit(o: wp.vec3, d: wp.vec3):
    """(t of the nearest pillar or MISS, its index, 1 if the cap was hit else 0)."""
    best = float(_MISS)
    best_k = int(0)
    cap = int(0)
    a = d[0] * d[0] + d[1] * d[1]
    for k in range(_PILLAR_COUNT):
        c = pillar_center(k)
        qx = o[0] - c[0]
        qy = o[1] - c[1]
        if a > 0.0:
            b = qx * d[0] + qy * d[1]
            disc = b * b - a * (qx * qx + qy * qy - _PILLAR_R * _PILLAR_R)
            if disc >= 0.0:
                t = (-b - wp.sqrt(disc)) / a
                z = o[2] + t * d[2]
                if t > 0.0 and z >= _GROUND_Z and z <= _PILLAR_TOP and (best < 0.0 or t < best):
                    best = t
                    best_k = k
                    cap = 0
        if d[2] < 0.0 and o[2] > _PILLAR_TOP:
            t = (_PILLAR_TOP - o[2]) / d[2]
            ex = qx + t * d[0]
            ey = qy + t * d[1]
            if ex * ex + ey * ey <= _PILLAR_R * _PILLAR_R and (best < 0.0 or t < best):
                best = t
                best_k = k
                cap = 1
    return best, best_k, cap


@wp.func
def first_hit(o: wp.vec3, d: wp.vec3):
    """(t, what, pillar index, cap flag): the nearest of object, ground and pillar, or the sky."""
    t = trace(o, d)
    what = int(_HIT_SKY)
    if t >= 0.0:
        what = _HIT_OBJECT
    if d[2] < 0.0:
        tg = (_GROUND_Z - o[2]) / d[2]
        if tg > 0.0 and (what == _HIT_SKY or tg < t):
            t = tg
            what = _HIT_GROUND
    tp, k, cap = pillar_hit(o, d)
    if tp >= 0.0 and (what == _HIT_SKY or tp < t):
        t = tp
        what = _HIT_PILLAR
    if what == _HIT_SKY:
        t = _MISS
    return t, what, k, cap


@wp.func
def ground_albedo(p: wp.vec3) -> wp.vec3:
    """Checker of GROUND_CELL squares, its contrast faded by 1 / (1 + (r / F)^2)."""
    r = wp.sqrt(p[0] * p[0] + p[1] * p[1])
    fade = 1.0 / (1.0 + (r / _GROUND_FADE) * (r / _GROUND_FADE))
    s = parity(wp.floor(p[0] / _GROUND_CELL) + wp.floor(p[1] / _GROUND_CELL))
    return wp.lerp(_GROUND_A, _GROUND_B, 0.5 + (s - 0.5) * fade)


@wp.func
def pillar_albedo(p: wp.vec3, k: int) -> wp.vec3:
    """Hue of pillar k, c_j = 0.5 + 0.4 cos(2 pi k / N + 2 pi j / 3), with pale bands in z."""
    phi = _TWO_PI * float(k) / float(_PILLAR_COUNT)
    third = _TWO_PI / 3.0
    hue = wp.vec3(0.5 + 0.4 * wp.cos(phi), 0.5 + 0.4 * wp.cos(phi + third), 0.5 + 0.4 * wp.cos(phi + 2.0 * third))
    band = parity((p[2] - _GROUND_Z) / _PILLAR_BAND)
    return wp.lerp(hue, _PILLAR_PALE, 0.6 * band)


@wp.func
def environment(d: wp.vec3) -> wp.vec3:
    """Colour at infinity along unit d: mountains below the skyline s(phi), sky gradient above."""
    elevation = wp.asin(wp.clamp(d[2], -1.0, 1.0))
    phi = wp.atan2(d[1], d[0])
    skyline = _SKYLINE_BASE
    for i in range(3):
        skyline = skyline + _WAVE_A[i] * wp.sin(_WAVE_F[i] * phi + _WAVE_P[i])
    if elevation < skyline:
        return wp.lerp(_MOUNTAIN_LOW, _MOUNTAIN_HIGH, wp.clamp(elevation / skyline, 0.0, 1.0))
    up = wp.clamp(d[2], 0.0, 1.0)
    return wp.lerp(_SKY_HORIZON, _SKY_ZENITH, up * (2.0 - up))


@wp.func
def lambert(albedo: wp.vec3, n: wp.vec3) -> wp.vec3:
    return albedo * (_AMBIENT + _DIFFUSE * wp.max(wp.dot(n, _LIGHT), 0.0))


@wp.func
def radiance(o: wp.vec3, d: wp.vec3):
    """(colour [0, 1]^3, t of the first hit or MISS) of the ray o + t d, d unit."""
    t, what, k, cap = first_hit(o, d)
    p = o + t * d
    c = environment(d)
    if what == _HIT_OBJECT:
        c = shade(p, d)
    elif what == _HIT_GROUND:
        c = lambert(ground_albedo(p), wp.vec3(0.0, 0.0, 1.0))
    elif what == _HIT_PILLAR:
        n = wp.vec3(0.0, 0.0, 1.0)
        if cap == 0:
            axis = pillar_center(k)
            n = wp.normalize(wp.vec3(p[0] - axis[0], p[1] - axis[1], 0.0))
        c = lambert(pillar_albedo(p, k), n)
    return c, t


@wp.kernel
def render_rays(first: int, origins: wp.array(dtype=wp.vec3), directions: wp.array(dtype=wp.vec3),
                rgb: wp.array(dtype=wp.vec3), depth: wp.array(dtype=wp.float32)):
    """rgb[i], depth[i] = radiance(o_i, d_i): colour and hit distance (MISS for the sky)."""
    i = first + wp.tid()
    c, t = radiance(origins[i], wp.normalize(directions[i]))
    rgb[i] = c
    depth[i] = t


@wp.kernel
def environment_rays(first: int, directions: wp.array(dtype=wp.vec3), rgb: wp.array(dtype=wp.vec3)):
    """rgb[i] = environment(d_i / |d_i|): the colour at infinity, with nothing in the way."""
    i = first + wp.tid()
    rgb[i] = environment(wp.normalize(directions[i]))


# Pixel (px, py) of view v, sample (sx, sy):  u = px + (sx + 1/2)/ss,  w = py + (sy + 1/2)/ss,
# d = normalize(R ((u - cx)/fx, -(w - cy)/fy, -1)).  out = mean over the ss^2 samples of the colour.
@wp.kernel
def render_views(
    first: int,
    c2w: wp.array3d(dtype=wp.float32),  # [V, 3, 4]
    intrinsics: wp.array2d(dtype=wp.float32),  # [V, 4] fx fy cx cy
    width: int,
    height: int,
    ss: int,
    out: wp.array(dtype=wp.vec3),  # [V * H * W] RGB
):
    i = first + wp.tid()
    v, px, py = view_pixel(i, width, height)
    o = wp.vec3(c2w[v, 0, 3], c2w[v, 1, 3], c2w[v, 2, 3])
    inv_ss = 1.0 / float(ss)
    total = wp.vec3(0.0, 0.0, 0.0)
    for sy in range(ss):
        for sx in range(ss):
            u = float(px) + (float(sx) + 0.5) * inv_ss
            d = view_direction(c2w, intrinsics, v, u, float(py) + (float(sy) + 0.5) * inv_ss)
            c, _t = radiance(o, d)
            total = total + c
    out[i] = total * (inv_ss * inv_ss)
