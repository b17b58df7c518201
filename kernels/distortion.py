"""Mip-NeRF 360's distortion loss on packed samples (one thread per ray) and its backward.

Samples of ray r are ``offsets[r] .. offsets[r+1]`` (sorted by ray, front to back). Midpoints
are taken relative to the ray's first one (the loss only sees their differences), which keeps
float32 prefix sums from cancelling at camera distances. With ``near`` > 0 every distance t is
first mapped to mip-NeRF 360's normalised distance s = 1 − near/t (inverse depth: near → 0,
infinity → 1), so that weight near the camera counts for more than weight far behind it.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def spacing(t: float, near: float):
    """t itself (near ≤ 0), or s = 1 − near/t."""
    if near > 0.0:
        return 1.0 - near / wp.max(t, near)
    return t


@wp.func
def spacing_slope(t: float, near: float):
    """du/dt of :func:`spacing`: 1 (near ≤ 0), near/t² from near on, 0 before it (clamped)."""
    if near > 0.0:
        if t >= near:
            return near / (t * t)
        return 0.0
    return 1.0


# In the spacing u = t or u = s(t): u_start_i, u_end_i of each sample, and
# m_i = (u_start_i + u_end_i)/2 − m_first, δ_i = u_end_i − u_start_i, with prefix sums
# W_<i = Σ_{j<i} w_j and M_<i = Σ_{j<i} w_j m_j:
#   L_r = Σ_{i,j} w_i w_j |m_i − m_j| + 1/3 Σ_i w_i² δ_i = Σ_i w_i (2 (m_i W_<i − M_<i) + w_i δ_i / 3)
@wp.kernel
def distortion_forward(
    first: int,
    weights: wp.array(dtype=float),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    offsets: wp.array(dtype=wp.int32),
    near: float,
    loss: wp.array(dtype=float),
):
    r = first + wp.tid()
    start = int(offsets[r])
    end = int(offsets[r + 1])
    total = float(0.0)
    w_before = float(0.0)
    wm_before = float(0.0)
    m_first = float(0.0)
    if start < end:
        m_first = 0.5 * (spacing(t_starts[start], near) + spacing(t_ends[start], near))
    for i in range(start, end):
        w = weights[i]
        u0 = spacing(t_starts[i], near)
        u1 = spacing(t_ends[i], near)
        m = 0.5 * (u0 + u1) - m_first
        total += w * (2.0 * (m * w_before - wm_before) + w * (u1 - u0) / 3.0)
        w_before += w
        wm_before += w * m
    loss[r] = total


# With W, M the ray's totals and W_>i = W − W_<i − w_i, M_>i = M − M_<i − w_i m_i:
#   ∂L_r/∂w_i = 2 (m_i W_<i − M_<i) + 2 (M_>i − m_i W_>i) + 2/3 w_i δ_i
# (a first pass over the ray sums W and M). With interval_grads, the intervals' gradients too
# (samples front to back, so m_j < m_i before i and > after it; L sees only differences of m):
#   ∂L_r/∂m_i = 2 w_i (W_<i − W_>i),   ∂L_r/∂δ_i = w_i² / 3,
#   ∂L_r/∂t_start_i = (∂L/∂m_i / 2 − ∂L/∂δ_i) u'(t_start_i),  ∂L_r/∂t_end_i = (∂L/∂m_i / 2 + ∂L/∂δ_i) u'(t_end_i).
@wp.kernel
def distortion_backward(
    first: int,
    weights: wp.array(dtype=float),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    offsets: wp.array(dtype=wp.int32),
    near: float,
    grad_loss: wp.array(dtype=float),
    interval_grads: int,
    grad_weights: wp.array(dtype=float),
    grad_t_starts: wp.array(dtype=float),
    grad_t_ends: wp.array(dtype=float),
):
    r = first + wp.tid()
    start = int(offsets[r])
    end = int(offsets[r + 1])
    if start >= end:
        return
    g = grad_loss[r]
    m_first = 0.5 * (spacing(t_starts[start], near) + spacing(t_ends[start], near))
    w_total = float(0.0)
    wm_total = float(0.0)
    for i in range(start, end):
        w_total += weights[i]
        wm_total += weights[i] * (0.5 * (spacing(t_starts[i], near) + spacing(t_ends[i], near)) - m_first)
    w_before = float(0.0)
    wm_before = float(0.0)
    for i in range(start, end):
        w = weights[i]
        u0 = spacing(t_starts[i], near)
        u1 = spacing(t_ends[i], near)
        m = 0.5 * (u0 + u1) - m_first
        w_after = w_total - w_before - w
        wm_after = wm_total - wm_before - w * m
        d = 2.0 * (m * w_before - wm_before) + 2.0 * (wm_after - m * w_after)
        grad_weights[i] = g * (d + 2.0 / 3.0 * w * (u1 - u0))
        if interval_grads != 0:
            along = w * (w_before - w_after)  # ∂L/∂m_i / 2
            width = w * w / 3.0
            grad_t_starts[i] = g * (along - width) * spacing_slope(t_starts[i], near)
            grad_t_ends[i] = g * (along + width) * spacing_slope(t_ends[i], near)
        w_before += w
        wm_before += w * m
