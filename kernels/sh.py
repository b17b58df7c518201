"""Real spherical harmonics of degree 4 (16 values) of unit view directions.

Directions carry no gradient in ngp-warp (they come from cameras), so there is no backward.
Constants and signs follow tiny-cuda-nn's SphericalHarmonics encoding.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


# Y_00 .. Y_33 of d = (x, y, z), written out in full (the standard real SH polynomials).
@wp.kernel
def sh_deg4(first: int, dirs: wp.array(dtype=wp.vec3), out: wp.array2d(dtype=wp.float32)):
    i = first + wp.tid()
    d = dirs[i]
    x = d[0]
    y = d[1]
    z = d[2]
    xx = x * x
    yy = y * y
    zz = z * z
    out[i, 0] = 0.28209479177387814
    out[i, 1] = -0.48860251190291987 * y
    out[i, 2] = 0.48860251190291987 * z
    out[i, 3] = -0.48860251190291987 * x
    out[i, 4] = 1.0925484305920792 * x * y
    out[i, 5] = -1.0925484305920792 * y * z
    out[i, 6] = 0.94617469575755997 * zz - 0.31539156525251999
    out[i, 7] = -1.0925484305920792 * x * z
    out[i, 8] = 0.54627421529603959 * (xx - yy)
    out[i, 9] = 0.59004358992664352 * y * (-3.0 * xx + yy)
    out[i, 10] = 2.8906114426405538 * x * y * z
    out[i, 11] = 0.45704579946446572 * y * (1.0 - 5.0 * zz)
    out[i, 12] = 0.3731763325901154 * z * (5.0 * zz - 3.0)
    out[i, 13] = 0.45704579946446572 * x * (1.0 - 5.0 * zz)
    out[i, 14] = 1.4453057213202769 * z * (xx - yy)
    out[i, 15] = 0.59004358992664352 * x * (-xx + 3.0 * yy)
