r"""The field's Warp kernels: the view directions' spherical harmonics and the density
activation of the no-gradient pass.

Spherical harmonics: real, of degree 4 (16 values) of unit view directions. Directions carry no
gradient in ngp-warp (they come from cameras), so there is no backward. Constants and signs
follow tiny-cuda-nn's SphericalHarmonics encoding.

Density activation: log-density → σ, zero outside the box,

.. math::

    \sigma = \begin{cases} \exp(h_0) & x \in [lo, hi] \\ 0 & \text{otherwise} \end{cases}

with ``aabb = (xmin, ymin, zmin, xmax, ymax, zmax)``; the truncated exponential of training
differs from ``exp`` only in its gradient. ``h_0`` comes from the MLP as float32 or as
bfloat16 bits (Warp has no bfloat16 type).
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


@wp.func_native("""
union { unsigned int u; float f; } c;
c.u = (unsigned int)(unsigned short)bits << 16;
return c.f;
""")
def bf16_to_float(bits: wp.int16) -> float: ...


@wp.func
def activate(h: float, x: wp.vec3, aabb: wp.array(dtype=wp.float32)) -> float:
    inside = bool(True)
    for d in range(3):
        inside = inside and x[d] >= aabb[d] and x[d] <= aabb[3 + d]
    return wp.where(inside, wp.exp(h), 0.0)


# σ_i = exp(h_i) when positions[i] lies in the box, else 0 (h float32 here, bfloat16 bits below)
@wp.kernel
def density_from_log(first: int, log_sigma: wp.array(dtype=wp.float32), positions: wp.array(dtype=wp.vec3),
                     aabb: wp.array(dtype=wp.float32), sigma: wp.array(dtype=wp.float32)):
    i = first + wp.tid()
    sigma[i] = activate(log_sigma[i], positions[i], aabb)


@wp.kernel
def density_from_log_bf16(first: int, log_sigma: wp.array(dtype=wp.int16), positions: wp.array(dtype=wp.vec3),
                          aabb: wp.array(dtype=wp.float32), sigma: wp.array(dtype=wp.float32)):
    i = first + wp.tid()
    sigma[i] = activate(bf16_to_float(log_sigma[i]), positions[i], aabb)
