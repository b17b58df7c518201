"""The procedural demo scene: an analytic, textured signed-distance scene, sphere-traced.

Four large smooth objects (z is up, as in the Blender scenes) inside [-1.5, 1.5]^3:

* a sphere with a longitude/latitude checker,
* a rounded box, turned about z, with stripes,
* a torus lying flat, with a hue wheel around its ring,
* a rounded upright cylinder with a vertical colour gradient,

lit by one directional light: albedo * (ambient + diffuse max(n.l, 0)) plus a Blinn-Phong
highlight ks max(n.h, 0)^shininess, which depends on the view direction. Each pixel averages
ss x ss stratified rays (alpha = covered fraction), so the images are exactly a box-filtered
rendering of the analytic scene. Not differentiable: there is no backward kernel.

The plain-Python constants below are shared with the float64 twin in
``ngp_warp/_reference/scene.py``.
"""

import math

import warp as wp

wp.set_module_options({"enable_backward": False})

# ---- scene description (plain Python; the kernel uses the wp.constant copies) -------------
BOUND = 1.5  # rays are traced only inside [-BOUND, BOUND]^3
MAX_STEPS = 160
HIT_EPS = 2.0e-4
NORMAL_EPS = 1.0e-3

SPHERE_CENTER = (0.45, 0.4, 0.1)
SPHERE_RADIUS = 0.5
BOX_CENTER = (-0.5, 0.4, -0.05)
BOX_HALF = (0.36, 0.36, 0.36)  # half extents, including the rounding
BOX_ROUND = 0.06
BOX_ANGLE = 0.5  # turn about +z, radians
TORUS_CENTER = (0.45, -0.5, -0.3)
TORUS_MAJOR = 0.42
TORUS_MINOR = 0.17
CYL_CENTER = (-0.45, -0.5, 0.05)
CYL_RADIUS = 0.28
CYL_HALF_HEIGHT = 0.45
CYL_ROUND = 0.05

CHECKER_CELLS = (8.0, 4.0)  # sphere: cells around (longitude) and from pole to pole
CHECKER_A = (0.9, 0.25, 0.2)
CHECKER_B = (0.95, 0.88, 0.7)
STRIPE_WIDTH = 0.16  # box stripes along its local x
STRIPE_A = (0.15, 0.35, 0.85)
STRIPE_B = (0.92, 0.93, 0.96)
HUE_BIAS, HUE_GAIN = 0.5, 0.45  # torus: c_k = bias + gain cos(phi + 2 pi k / 3)
GRADIENT_BOTTOM = (0.95, 0.75, 0.15)  # cylinder
GRADIENT_TOP = (0.2, 0.65, 0.35)

_l = (0.4, -0.3, 0.85)
_ln = math.sqrt(sum(c * c for c in _l))
LIGHT_DIR = tuple(c / _ln for c in _l)  # unit, towards the light
AMBIENT = 0.35
DIFFUSE = 0.65
SPECULAR = (0.45, 0.25, 0.35, 0.3)  # ks per object: sphere, box, torus, cylinder
SHININESS = (32.0, 16.0, 24.0, 20.0)

# ---- Warp copies ----------------------------------------------------------------------------
_BOUND = wp.constant(BOUND)
_MAX_STEPS = wp.constant(MAX_STEPS)
_HIT_EPS = wp.constant(HIT_EPS)
_NORMAL_EPS = wp.constant(NORMAL_EPS)
_SPHERE_C = wp.constant(wp.vec3(*SPHERE_CENTER))
_SPHERE_R = wp.constant(SPHERE_RADIUS)
_BOX_C = wp.constant(wp.vec3(*BOX_CENTER))
_BOX_H = wp.constant(wp.vec3(*BOX_HALF))
_BOX_ROUND = wp.constant(BOX_ROUND)
_BOX_COS = wp.constant(math.cos(BOX_ANGLE))
_BOX_SIN = wp.constant(math.sin(BOX_ANGLE))
_TORUS_C = wp.constant(wp.vec3(*TORUS_CENTER))
_TORUS_R = wp.constant(TORUS_MAJOR)
_TORUS_r = wp.constant(TORUS_MINOR)
_CYL_C = wp.constant(wp.vec3(*CYL_CENTER))
_CYL_R = wp.constant(CYL_RADIUS)
_CYL_H = wp.constant(CYL_HALF_HEIGHT)
_CYL_ROUND = wp.constant(CYL_ROUND)
_CHECK_U = wp.constant(CHECKER_CELLS[0])
_CHECK_V = wp.constant(CHECKER_CELLS[1])
_CHECK_A = wp.constant(wp.vec3(*CHECKER_A))
_CHECK_B = wp.constant(wp.vec3(*CHECKER_B))
_STRIPE_W = wp.constant(STRIPE_WIDTH)
_STRIPE_A = wp.constant(wp.vec3(*STRIPE_A))
_STRIPE_B = wp.constant(wp.vec3(*STRIPE_B))
_HUE_BIAS = wp.constant(HUE_BIAS)
_HUE_GAIN = wp.constant(HUE_GAIN)
_GRAD_BOTTOM = wp.constant(wp.vec3(*GRADIENT_BOTTOM))
_GRAD_TOP = wp.constant(wp.vec3(*GRADIENT_TOP))
_LIGHT = wp.constant(wp.vec3(*LIGHT_DIR))
_AMBIENT = wp.constant(AMBIENT)
_DIFFUSE = wp.constant(DIFFUSE)
_KS = wp.constant(wp.vec4(*SPECULAR))
_SHINE = wp.constant(wp.vec4(*SHININESS))
_TWO_PI = wp.constant(2.0 * math.pi)


@wp.func
def parity(x: float) -> float:
    """floor(x) mod 2, as 0.0 or 1.0 (also for negative x)."""
    return wp.floor(x) - 2.0 * wp.floor(0.5 * x)


@wp.func
def box_local(p: wp.vec3) -> wp.vec3:
    """World point -> the box's frame (undo the turn about z)."""
    q = p - _BOX_C
    return wp.vec3(_BOX_COS * q[0] + _BOX_SIN * q[1], -_BOX_SIN * q[0] + _BOX_COS * q[1], q[2])


# Exact distances: sphere |q| - r; rounded box |max(|q| - b', 0)| + min(max_k(|q_k| - b'_k), 0) - rho
# with b' = b - rho; torus |(|q_xy| - R, q_z)| - r; rounded cylinder likewise in (|q_xy|, |q_z|).
@wp.func
def sd_sphere(p: wp.vec3) -> float:
    return wp.length(p - _SPHERE_C) - _SPHERE_R


@wp.func
def sd_box(p: wp.vec3) -> float:
    q = box_local(p)
    b = _BOX_H - wp.vec3(_BOX_ROUND, _BOX_ROUND, _BOX_ROUND)
    d = wp.vec3(wp.abs(q[0]) - b[0], wp.abs(q[1]) - b[1], wp.abs(q[2]) - b[2])
    outside = wp.vec3(wp.max(d[0], 0.0), wp.max(d[1], 0.0), wp.max(d[2], 0.0))
    return wp.length(outside) + wp.min(wp.max(d[0], wp.max(d[1], d[2])), 0.0) - _BOX_ROUND


@wp.func
def sd_torus(p: wp.vec3) -> float:
    q = p - _TORUS_C
    a = wp.sqrt(q[0] * q[0] + q[1] * q[1]) - _TORUS_R
    return wp.sqrt(a * a + q[2] * q[2]) - _TORUS_r


@wp.func
def sd_cylinder(p: wp.vec3) -> float:
    q = p - _CYL_C
    dr = wp.sqrt(q[0] * q[0] + q[1] * q[1]) - (_CYL_R - _CYL_ROUND)
    dz = wp.abs(q[2]) - (_CYL_H - _CYL_ROUND)
    outside = wp.sqrt(wp.max(dr, 0.0) * wp.max(dr, 0.0) + wp.max(dz, 0.0) * wp.max(dz, 0.0))
    return wp.min(wp.max(dr, dz), 0.0) + outside - _CYL_ROUND


@wp.func
def scene_sdf(p: wp.vec3) -> float:
    return wp.min(wp.min(sd_sphere(p), sd_box(p)), wp.min(sd_torus(p), sd_cylinder(p)))


@wp.func
def nearest_object(p: wp.vec3) -> int:
    """0 sphere, 1 box, 2 torus, 3 cylinder: the object whose surface is closest to p."""
    best = sd_sphere(p)
    k = int(0)
    d = sd_box(p)
    if d < best:
        best = d
        k = 1
    d = sd_torus(p)
    if d < best:
        best = d
        k = 2
    d = sd_cylinder(p)
    if d < best:
        k = 3
    return k


@wp.func
def albedo(p: wp.vec3, k: int) -> wp.vec3:
    """Procedural texture of object k at surface point p."""
    if k == 0:  # checker in (longitude, latitude)
        q = wp.normalize(p - _SPHERE_C)
        u = (wp.atan2(q[1], q[0]) / _TWO_PI + 0.5) * _CHECK_U
        v = wp.acos(wp.clamp(q[2], -1.0, 1.0)) / (0.5 * _TWO_PI) * _CHECK_V
        return wp.lerp(_CHECK_A, _CHECK_B, parity(wp.floor(u) + wp.floor(v)))
    if k == 1:  # stripes across the box's local x
        return wp.lerp(_STRIPE_A, _STRIPE_B, parity(box_local(p)[0] / _STRIPE_W))
    if k == 2:  # hue wheel around the ring
        q = p - _TORUS_C
        phi = wp.atan2(q[1], q[0])
        third = _TWO_PI / 3.0
        return wp.vec3(
            _HUE_BIAS + _HUE_GAIN * wp.cos(phi),
            _HUE_BIAS + _HUE_GAIN * wp.cos(phi + third),
            _HUE_BIAS + _HUE_GAIN * wp.cos(phi + 2.0 * third),
        )
    h = wp.clamp((p[2] - _CYL_C[2] + _CYL_H) / (2.0 * _CYL_H), 0.0, 1.0)  # vertical gradient
    return wp.lerp(_GRAD_BOTTOM, _GRAD_TOP, h)


@wp.func
def surface_normal(p: wp.vec3) -> wp.vec3:
    """Tetrahedral finite-difference gradient of the scene SDF, normalised."""
    e = _NORMAL_EPS
    a = wp.vec3(1.0, -1.0, -1.0)
    b = wp.vec3(-1.0, -1.0, 1.0)
    c = wp.vec3(-1.0, 1.0, -1.0)
    d = wp.vec3(1.0, 1.0, 1.0)
    g = a * scene_sdf(p + e * a) + b * scene_sdf(p + e * b) + c * scene_sdf(p + e * c) + d * scene_sdf(p + e * d)
    return wp.normalize(g)


@wp.func
def shade(p: wp.vec3, ray_d: wp.vec3) -> wp.vec3:
    """c = clamp(albedo (ambient + diffuse max(n.l, 0)) + ks max(n.h, 0)^s, 0, 1), h = |l - d|^-1 (l - d)."""
    k = nearest_object(p)
    n = surface_normal(p)
    diff = wp.max(wp.dot(n, _LIGHT), 0.0)
    h = wp.normalize(_LIGHT - ray_d)
    spec = _KS[k] * wp.pow(wp.max(wp.dot(n, h), 0.0), _SHINE[k])
    c = albedo(p, k) * (_AMBIENT + _DIFFUSE * diff) + wp.vec3(spec, spec, spec)
    return wp.vec3(wp.clamp(c[0], 0.0, 1.0), wp.clamp(c[1], 0.0, 1.0), wp.clamp(c[2], 0.0, 1.0))


@wp.func
def trace(o: wp.vec3, d: wp.vec3) -> float:
    """Sphere tracing inside the bounding cube: the hit distance t, or -1 for a miss.

    t_{k+1} = t_k + f(o + t_k d) from the cube entry; hit when f < eps, miss past the exit."""
    t0 = float(0.0)
    t1 = float(1.0e30)
    for a in range(3):
        inv = 1.0 / d[a]  # +-inf for axis-parallel rays: the slab test still works
        ta = (-_BOUND - o[a]) * inv
        tb = (_BOUND - o[a]) * inv
        t0 = wp.max(t0, wp.min(ta, tb))
        t1 = wp.min(t1, wp.max(ta, tb))
    result = float(-1.0)
    if t0 < t1:
        t = t0
        for _step in range(_MAX_STEPS):
            if t > t1:
                break
            f = scene_sdf(o + t * d)
            if f < _HIT_EPS:
                result = t
                break
            t = t + f
    return result


# Item i of a [V, H, W] launch: view v = i div (H W), row py, column px of pixel i mod (H W).
@wp.func
def view_pixel(i: int, width: int, height: int):
    n_pix = width * height
    v = i // n_pix
    pix = i - v * n_pix
    py = pix // width
    return v, pix - py * width, py


# The direction through image point (u, w) of view v (pixel units, OpenGL camera axes):
# d = normalize(R ((u - cx)/fx, -(w - cy)/fy, -1)), R the first three columns of c2w[v].
@wp.func
def view_direction(c2w: wp.array3d(dtype=wp.float32), intrinsics: wp.array2d(dtype=wp.float32), v: int,
                   u: float, w: float) -> wp.vec3:
    x = (u - intrinsics[v, 2]) / intrinsics[v, 0]
    y = -(w - intrinsics[v, 3]) / intrinsics[v, 1]
    return wp.normalize(
        wp.vec3(
            c2w[v, 0, 0] * x + c2w[v, 0, 1] * y - c2w[v, 0, 2],
            c2w[v, 1, 0] * x + c2w[v, 1, 1] * y - c2w[v, 1, 2],
            c2w[v, 2, 0] * x + c2w[v, 2, 1] * y - c2w[v, 2, 2],
        )
    )


# Pixel (px, py) of view v, sample (sx, sy):  u = px + (sx + 1/2)/ss,  w = py + (sy + 1/2)/ss,
# d = normalize(R ((u - cx)/fx, -(w - cy)/fy, -1)).  out = (mean colour of the hits, hits / ss^2).
@wp.kernel
def render_views(
    first: int,
    c2w: wp.array3d(dtype=wp.float32),  # [V, 3, 4]
    intrinsics: wp.array2d(dtype=wp.float32),  # [V, 4] fx fy cx cy
    width: int,
    height: int,
    ss: int,
    out: wp.array2d(dtype=wp.float32),  # [V * H * W, 4] straight RGB, alpha
):
    i = first + wp.tid()
    v, px, py = view_pixel(i, width, height)
    o = wp.vec3(c2w[v, 0, 3], c2w[v, 1, 3], c2w[v, 2, 3])
    inv_ss = 1.0 / float(ss)
    rgb = wp.vec3(0.0, 0.0, 0.0)
    hits = float(0.0)
    for sy in range(ss):
        for sx in range(ss):
            u = float(px) + (float(sx) + 0.5) * inv_ss
            d = view_direction(c2w, intrinsics, v, u, float(py) + (float(sy) + 0.5) * inv_ss)
            t = trace(o, d)
            if t >= 0.0:
                rgb = rgb + shade(o + t * d, d)
                hits = hits + 1.0
    if hits > 0.0:
        rgb = rgb / hits
    out[i, 0] = rgb[0]
    out[i, 1] = rgb[1]
    out[i, 2] = rgb[2]
    out[i, 3] = hits * inv_ss * inv_ss
