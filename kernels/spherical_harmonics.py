r"""Real spherical harmonics of degree 4 (bands 0..3, 16 values) of unit view directions, and
their adjoint. Constants and signs follow tiny-cuda-nn's SphericalHarmonics encoding.

.. math::

    Y(d) \in \mathbb{R}^{16}, \qquad \frac{\partial L}{\partial d} = \sum_k \frac{\partial L}{\partial Y_k}
    \frac{\partial Y_k}{\partial d}
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


# Y_00 .. Y_33 of d = (x, y, z), written out in full (the standard real SH polynomials). Item
# 4i + q writes values 4q .. 4q + 3 of direction i: consecutive threads store consecutive 16 bytes.
@wp.kernel
def sh_deg4(first: int, dirs: wp.array(dtype=wp.vec3), out: wp.array(dtype=wp.vec4)):
    item = first + wp.tid()
    i = item // 4
    q = item - 4 * i
    d = dirs[i]
    x = d[0]
    y = d[1]
    z = d[2]
    xx = x * x
    yy = y * y
    zz = z * z
    if q == 0:
        out[item] = wp.vec4(0.28209479177387814, -0.48860251190291987 * y, 0.48860251190291987 * z,
                            -0.48860251190291987 * x)
    elif q == 1:
        out[item] = wp.vec4(1.0925484305920792 * x * y, -1.0925484305920792 * y * z,
                            0.94617469575755997 * zz - 0.31539156525251999, -1.0925484305920792 * x * z)
    elif q == 2:
        out[item] = wp.vec4(0.54627421529603959 * (xx - yy), 0.59004358992664352 * y * (-3.0 * xx + yy),
                            2.8906114426405538 * x * y * z, 0.45704579946446572 * y * (1.0 - 5.0 * zz))
    else:
        out[item] = wp.vec4(0.3731763325901154 * z * (5.0 * zz - 3.0), 0.45704579946446572 * x * (1.0 - 5.0 * zz),
                            1.4453057213202769 * z * (xx - yy), 0.59004358992664352 * x * (-xx + 3.0 * yy))


# The adjoint: dL/dd = Σ_k g_k ∂Y_k/∂d, each polynomial above differentiated by hand (one thread
# per direction; g is the gradient of the values, [N, 16] row-major).
@wp.kernel
def sh_deg4_backward(first: int, dirs: wp.array(dtype=wp.vec3), grad_values: wp.array(dtype=float),
                     grad_dirs: wp.array(dtype=wp.vec3)):
    i = first + wp.tid()
    x = dirs[i][0]
    y = dirs[i][1]
    z = dirs[i][2]
    zz = z * z
    xx_yy = x * x - y * y
    a = 0.48860251190291987
    b = 1.0925484305920792
    c = 0.94617469575755997
    f = 0.54627421529603959
    g = 0.59004358992664352
    h = 2.8906114426405538
    m = 0.45704579946446572
    n = 0.3731763325901154
    p = 1.4453057213202769
    gv = wp.vec3(0.0, 0.0, 0.0)
    gv += grad_values[16 * i + 1] * wp.vec3(0.0, -a, 0.0)
    gv += grad_values[16 * i + 2] * wp.vec3(0.0, 0.0, a)
    gv += grad_values[16 * i + 3] * wp.vec3(-a, 0.0, 0.0)
    gv += grad_values[16 * i + 4] * wp.vec3(b * y, b * x, 0.0)
    gv += grad_values[16 * i + 5] * wp.vec3(0.0, -b * z, -b * y)
    gv += grad_values[16 * i + 6] * wp.vec3(0.0, 0.0, 2.0 * c * z)
    gv += grad_values[16 * i + 7] * wp.vec3(-b * z, 0.0, -b * x)
    gv += grad_values[16 * i + 8] * wp.vec3(2.0 * f * x, -2.0 * f * y, 0.0)
    gv += grad_values[16 * i + 9] * wp.vec3(-6.0 * g * x * y, -3.0 * g * xx_yy, 0.0)
    gv += grad_values[16 * i + 10] * wp.vec3(h * y * z, h * x * z, h * x * y)
    gv += grad_values[16 * i + 11] * wp.vec3(0.0, m * (1.0 - 5.0 * zz), -10.0 * m * y * z)
    gv += grad_values[16 * i + 12] * wp.vec3(0.0, 0.0, n * (15.0 * zz - 3.0))
    gv += grad_values[16 * i + 13] * wp.vec3(m * (1.0 - 5.0 * zz), 0.0, -10.0 * m * x * z)
    gv += grad_values[16 * i + 14] * wp.vec3(2.0 * p * x * z, -2.0 * p * y * z, p * xx_yy)
    gv += grad_values[16 * i + 15] * wp.vec3(-3.0 * g * xx_yy, 6.0 * g * x * y, 0.0)
    grad_dirs[i] = gv
