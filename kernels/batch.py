"""Training batches in one launch: random pixels of random training images → rays, targets and
random backgrounds (the camera model of ``ngp_warp.data.cameras``)."""

import warp as wp

wp.set_module_options({"enable_backward": False})

UNDISTORT_ITERATIONS = 10  # Newton steps, here and in ngp_warp.data.cameras; fixed, so nothing syncs
LENS_PINHOLE = 0  # lens_model codes, shared with ngp_warp.data.cameras
LENS_OPENCV = 1
LENS_FISHEYE = 2

vec6 = wp.types.vector(length=6, dtype=float)  # k1, k2, k3, k4, p1, p2


# OpenCV radial-tangential distortion inverted by Newton's method from (xd, yd):
#   distort(x, y) = (x (1 + ρ) + 2 p1 x y + p2 (r² + 2x²),  y (1 + ρ) + 2 p2 x y + p1 (r² + 2y²)),
#   ρ = k1 r² + k2 r⁴ + k3 r⁶;   (x, y) ← (x, y) − J⁻¹ (distort(x, y) − (xd, yd)).
@wp.func
def undistort(xd: float, yd: float, k: vec6):
    k1 = k[0]
    k2 = k[1]
    k3 = k[2]
    p1 = k[4]
    p2 = k[5]
    x = xd
    y = yd
    for _ in range(UNDISTORT_ITERATIONS):
        r2 = x * x + y * y
        rho = r2 * (k1 + r2 * (k2 + k3 * r2))
        drho = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2))
        ex = x * (1.0 + rho) + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
        ey = y * (1.0 + rho) + 2.0 * p2 * x * y + p1 * (r2 + 2.0 * y * y) - yd
        jxx = 1.0 + rho + drho * x * x + 2.0 * p1 * y + 6.0 * p2 * x
        jxy = drho * x * y + 2.0 * p1 * x + 2.0 * p2 * y
        jyx = drho * x * y + 2.0 * p2 * y + 2.0 * p1 * x
        jyy = 1.0 + rho + drho * y * y + 2.0 * p2 * x + 6.0 * p1 * y
        det = jxx * jyy - jxy * jyx
        if wp.abs(det) < 1.0e-12:
            det = 1.0e-12
        x = x - (jyy * ex - jxy * ey) / det
        y = y - (jxx * ey - jyx * ex) / det
    return wp.vec2(x, y)


# OpenCV fisheye (equidistant) lens: a ray at angle θ from the axis lands at radius
#   r_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸) along its azimuth (xd, yd) / r_d;
# θ by Newton from θ = r_d, then the camera-frame ray (OpenCV axes, z forward) is
#   (sin θ xd / r_d, sin θ yd / r_d, cos θ).
@wp.func
def fisheye_ray(xd: float, yd: float, k: vec6):
    rd = wp.sqrt(xd * xd + yd * yd)
    theta = rd
    for _ in range(UNDISTORT_ITERATIONS):
        t2 = theta * theta
        f = theta * (1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])))) - rd
        df = 1.0 + t2 * (3.0 * k[0] + t2 * (5.0 * k[1] + t2 * (7.0 * k[2] + t2 * 9.0 * k[3])))
        if wp.abs(df) < 1.0e-12:
            df = 1.0e-12
        theta = theta - f / df
    s = 1.0
    if rd > 1.0e-12:
        s = wp.sin(theta) / rd
    return wp.vec3(xd * s, yd * s, wp.cos(theta))


# The unit world direction through image point (u, v) (pixels) of a camera with intrinsics
# f = (fx, fy, cx, cy) and camera-to-world [R | t] at c2w[m : m + 12] (row-major):
#   x = (u − cx) / fx,  y = (v − cy) / fy  (undistorted for LENS_OPENCV),
#   d = R (x, −y, −1) / |R (x, −y, −1)|  (LENS_FISHEYE: R (x', −y', −z') / |·| for
#   (x', y', z') = fisheye_ray(x, y)).
@wp.func
def camera_ray(u: float, v: float, f: wp.vec4, lens_model: int, k: vec6, c2w: wp.array(dtype=float), m: int):
    x = (u - f[2]) / f[0]
    y = (v - f[3]) / f[1]
    if lens_model == LENS_OPENCV:
        p = undistort(x, y, k)
        x = p[0]
        y = p[1]
    r = wp.vec3(x, y, 1.0)
    if lens_model == LENS_FISHEYE:
        r = fisheye_ray(x, y, k)
    d = wp.vec3(
        c2w[m + 0] * r[0] - c2w[m + 1] * r[1] - c2w[m + 2] * r[2],
        c2w[m + 4] * r[0] - c2w[m + 5] * r[1] - c2w[m + 6] * r[2],
        c2w[m + 8] * r[0] - c2w[m + 9] * r[1] - c2w[m + 10] * r[2],
    )
    return wp.normalize(d)


# Ray i: sub-ray s = i mod sub² of pixel q = i div sub²; the pixel's image k and (px, py) are
# drawn uniformly (Warp's RNG keyed by seed and q, so a pixel's sub-rays agree; its first
# sub-ray writes the pixel's row q of pixels, target and background), and drawn again, up to
# redraws times, while masks[k, py, px] (uint8 [N, H, W], when redraws > 0) is 0; then
#   d = camera_ray(px + ox, py + oy) of image k,  o = t,
#   (ox, oy) = ((s mod sub) + 1/2, (s div sub) + 1/2) / sub  (the pixel centre for sub = 1);
#   bg ~ U[0, 1)³ with an alpha channel (else white), target = rgb a + bg (1 − a), values / 255.
@wp.kernel
def sample_pixels(
    first: int,
    seed: int,
    sub: int,
    n_images: int,
    width: int,
    height: int,
    channels: int,
    lens_model: int,
    images: wp.array(dtype=wp.uint8),
    masks: wp.array(dtype=wp.uint8),
    redraws: int,
    c2w: wp.array(dtype=float),
    intrinsics: wp.array(dtype=wp.vec4),
    distortion: wp.array(dtype=vec6),
    pixels: wp.array(dtype=wp.vec3i),
    rays_o: wp.array(dtype=wp.vec3),
    rays_d: wp.array(dtype=wp.vec3),
    target: wp.array(dtype=wp.vec3),
    background: wp.array(dtype=wp.vec3),
):
    i = first + wp.tid()
    q = i // (sub * sub)
    s = i - q * sub * sub
    rng = wp.rand_init(seed, q)
    k = wp.randi(rng, 0, n_images)
    px = wp.randi(rng, 0, width)
    py = wp.randi(rng, 0, height)
    for _ in range(redraws):
        if masks[(k * height + py) * width + px] != wp.uint8(0):
            break
        k = wp.randi(rng, 0, n_images)
        px = wp.randi(rng, 0, width)
        py = wp.randi(rng, 0, height)

    ox = (float(s % sub) + 0.5) / float(sub)
    oy = (float(s // sub) + 0.5) / float(sub)
    m = k * 12  # row-major [3, 4]
    rays_o[i] = wp.vec3(c2w[m + 3], c2w[m + 7], c2w[m + 11])
    rays_d[i] = camera_ray(float(px) + ox, float(py) + oy, intrinsics[k], lens_model, distortion[k], c2w, m)

    p = ((k * height + py) * width + px) * channels
    rgb = wp.vec3(float(images[p]), float(images[p + 1]), float(images[p + 2])) / 255.0
    bg = wp.vec3(1.0, 1.0, 1.0)
    if channels == 4:
        bg = wp.vec3(wp.randf(rng), wp.randf(rng), wp.randf(rng))
        a = float(images[p + 3]) / 255.0
        rgb = rgb * a + bg * (1.0 - a)
    if s == 0:
        pixels[q] = wp.vec3i(k, px, py)
        background[q] = bg
        target[q] = rgb


# Pixel i = py·width + px of one camera (c2w [3, 4] row-major, intrinsics f, lens k):
#   o = t,  d = camera_ray(px + 1/2 + dx, py + 1/2 + dy)  (a sub-pixel shift (dx, dy) in pixels).
@wp.kernel
def view_rays(
    first: int,
    width: int,
    dx: float,
    dy: float,
    lens_model: int,
    c2w: wp.array(dtype=float),
    intrinsics: wp.array(dtype=wp.vec4),
    distortion: wp.array(dtype=vec6),
    rays_o: wp.array(dtype=wp.vec3),
    rays_d: wp.array(dtype=wp.vec3),
):
    i = first + wp.tid()
    py = i // width
    px = i - py * width
    rays_o[i] = wp.vec3(c2w[3], c2w[7], c2w[11])
    rays_d[i] = camera_ray(float(px) + 0.5 + dx, float(py) + 0.5 + dy, intrinsics[0], lens_model, distortion[0], c2w, 0)
