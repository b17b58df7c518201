r"""The field's Warp kernel: the density activation of the no-gradient pass (the view
directions' spherical harmonics are kernels/spherical_harmonics.py), log-density → σ, zero
outside the box,

.. math::

    \sigma = \begin{cases} \exp(h_0) & x \in [lo, hi] \\ 0 & \text{otherwise} \end{cases}

with ``aabb = (xmin, ymin, zmin, xmax, ymax, zmax)``; the truncated exponential of training
differs from ``exp`` only in its gradient. ``h_0`` comes from the MLP as float32 or as
bfloat16 bits (Warp has no bfloat16 type).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


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
