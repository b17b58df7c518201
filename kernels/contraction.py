r"""Scene contraction for unbounded scenes: mip-NeRF 360's (L2) and nerfstudio's L∞ variant.

A world point p is first normalised by the inner box (centre c, half extents h, from an
``aabb`` = xmin, ymin, zmin, xmax, ymax, zmax), then contracted radially:

.. math::

    x = (p - c) \oslash h, \qquad m = \|x\|, \qquad
    C(x) = \begin{cases} x & m \le 1 \\ (2 - 1/m)\, x / m & m > 1 \end{cases}

with :math:`\|\cdot\|` the L2 norm (``kind`` 0, mip-NeRF 360: the unit ball, the ellipsoid
inscribed in the box, stays linear) or the L∞ norm (``kind`` 1, nerfstudio's ``order=inf``: the
whole box stays linear). The image is the open ball / cube of radius 2. nerfacc's
``UN_BOUNDED_SPHERE`` normalises the same way and then maps to [0, 1]^3 by y / 4 + 1/2.

The inverse, for n = ‖y‖ (clamped to ``MAX_CONTRACTED`` = 2 − 2^-20, so ‖x‖ ≤ 2^20):

.. math::

    C^{-1}(y) = y \text{ if } n \le 1, \qquad C^{-1}(y) = \frac{y}{n (2 - n)} \text{ otherwise.}

The contracted speed of a world direction d at p is the length of the directional derivative
(f(m) = 2 − 1/m, f' = 1/m², ∂m the gradient of the norm: x/m for L2, sign(x_k) e_k for L∞ with
k the largest |x_k|):

.. math::

    J v = \frac{f}{m} v + \frac{2 (1 - m)}{m^3} (\partial m \cdot v)\, x, \qquad v = d \oslash h,
    \qquad \text{speed} = \|J v\|_2 \quad (= \|v\|_2 \text{ for } m \le 1).

A world segment of length Δy / speed at p spans a contracted length Δy to first order: the march
steps in world space and evaluates the field at C(x). Forward only (no backward kernels): the
positions come from the march and never need gradients.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

L2 = 0  # kind flags
LINF = 1
MAX_CONTRACTED = 2.0 - 2.0**-20

_MAX_CONTRACTED = wp.constant(MAX_CONTRACTED)


@wp.func
def kind_norm(x: wp.vec3, kind: int) -> float:
    """‖x‖₂ (kind 0) or ‖x‖∞ (kind 1)."""
    if kind == 1:
        return wp.max(wp.abs(x[0]), wp.max(wp.abs(x[1]), wp.abs(x[2])))
    return wp.length(x)


@wp.func
def norm_gradient(x: wp.vec3, m: float, kind: int) -> wp.vec3:
    """∂‖x‖/∂x for m = ‖x‖ > 0: x / m (L2) or sign(x_k) e_k, k = argmax |x_k| (L∞, first on ties)."""
    if kind == 1:
        k = int(0)
        if wp.abs(x[1]) > wp.abs(x[k]):
            k = 1
        if wp.abs(x[2]) > wp.abs(x[k]):
            k = 2
        g = wp.vec3(0.0, 0.0, 0.0)
        g[k] = wp.sign(x[k])
        return g
    return x / m


@wp.func
def normalize_point(p: wp.vec3, aabb: wp.array(dtype=wp.float32)) -> wp.vec3:
    """World point -> x = (p - c) / h of the inner box."""
    x = wp.vec3(0.0, 0.0, 0.0)
    for a in range(3):
        x[a] = (p[a] - 0.5 * (aabb[a] + aabb[3 + a])) / (0.5 * (aabb[3 + a] - aabb[a]))
    return x


@wp.func
def denormalize_point(x: wp.vec3, aabb: wp.array(dtype=wp.float32)) -> wp.vec3:
    """x -> world point c + h x."""
    p = wp.vec3(0.0, 0.0, 0.0)
    for a in range(3):
        p[a] = 0.5 * (aabb[a] + aabb[3 + a]) + 0.5 * (aabb[3 + a] - aabb[a]) * x[a]
    return p


@wp.func
def contract(x: wp.vec3, kind: int) -> wp.vec3:
    """C(x) of a normalised point (see the module equations)."""
    m = kind_norm(x, kind)
    if m <= 1.0:
        return x
    return ((2.0 - 1.0 / m) / m) * x


@wp.func
def uncontract(y: wp.vec3, kind: int) -> wp.vec3:
    """C^-1(y), with ‖y‖ clamped to MAX_CONTRACTED."""
    n = kind_norm(y, kind)
    if n <= 1.0:
        return y
    n_c = wp.min(n, _MAX_CONTRACTED)
    return y * (1.0 / (n * (2.0 - n_c)))


@wp.func
def contracted_speed(x: wp.vec3, v: wp.vec3, kind: int) -> float:
    """‖J(x) v‖ of a normalised point x and normalised direction v = d / h."""
    m = kind_norm(x, kind)
    if m <= 1.0:
        return wp.length(v)
    g = norm_gradient(x, m, kind)
    jv = ((2.0 - 1.0 / m) / m) * v + (2.0 * (1.0 - m) / (m * m * m) * wp.dot(g, v)) * x
    return wp.length(jv)


@wp.kernel
def contract_points(first: int, points: wp.array(dtype=wp.vec3), aabb: wp.array(dtype=wp.float32), kind: int,
                    out: wp.array(dtype=wp.vec3)):
    i = first + wp.tid()
    out[i] = contract(normalize_point(points[i], aabb), kind)


@wp.kernel
def uncontract_points(first: int, contracted: wp.array(dtype=wp.vec3), aabb: wp.array(dtype=wp.float32),
                      kind: int, out: wp.array(dtype=wp.vec3)):
    i = first + wp.tid()
    out[i] = denormalize_point(uncontract(contracted[i], kind), aabb)


@wp.kernel
def world_step_lengths(first: int, points: wp.array(dtype=wp.vec3), directions: wp.array(dtype=wp.vec3),
                       aabb: wp.array(dtype=wp.float32), kind: int, contracted_step: float,
                       out: wp.array(dtype=wp.float32)):
    """out = Δy / ‖J(x) (d ⊘ h)‖: the world length whose contracted length is Δy."""
    i = first + wp.tid()
    d = directions[i]
    v = wp.vec3(0.0, 0.0, 0.0)
    for a in range(3):
        v[a] = d[a] / (0.5 * (aabb[3 + a] - aabb[a]))
    out[i] = contracted_step / contracted_speed(normalize_point(points[i], aabb), v, kind)
