"""Mip-NeRF 360's distortion loss on packed samples (one thread per ray) and its backward.

Samples of ray r are ``offsets[r] .. offsets[r+1]`` (sorted by ray, front to back). Midpoints
are taken relative to the ray's first one (the loss only sees their differences), which keeps
float32 prefix sums from cancelling at camera distances.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


# m_i = (t_start_i + t_end_i)/2 − m_first, δ_i = t_end_i − t_start_i, with prefix sums
# W_<i = Σ_{j<i} w_j and M_<i = Σ_{j<i} w_j m_j:
#   L_r = Σ_{i,j} w_i w_j |m_i − m_j| + 1/3 Σ_i w_i² δ_i = Σ_i w_i (2 (m_i W_<i − M_<i) + w_i δ_i / 3)
@wp.kernel
def distortion_forward(
    first: int,
    weights: wp.array(dtype=float),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    offsets: wp.array(dtype=wp.int32),
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
        m_first = 0.5 * (t_starts[start] + t_ends[start])
    for i in range(start, end):
        w = weights[i]
        m = 0.5 * (t_starts[i] + t_ends[i]) - m_first
        total += w * (2.0 * (m * w_before - wm_before) + w * (t_ends[i] - t_starts[i]) / 3.0)
        w_before += w
        wm_before += w * m
    loss[r] = total


# With W, M the ray's totals and W_>i = W − W_<i − w_i, M_>i = M − M_<i − w_i m_i:
#   ∂L_r/∂w_i = 2 (m_i W_<i − M_<i) + 2 (M_>i − m_i W_>i) + 2/3 w_i δ_i
# (a first pass over the ray sums W and M).
@wp.kernel
def distortion_backward(
    first: int,
    weights: wp.array(dtype=float),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    offsets: wp.array(dtype=wp.int32),
    grad_loss: wp.array(dtype=float),
    grad_weights: wp.array(dtype=float),
):
    r = first + wp.tid()
    start = int(offsets[r])
    end = int(offsets[r + 1])
    if start >= end:
        return
    g = grad_loss[r]
    m_first = 0.5 * (t_starts[start] + t_ends[start])
    w_total = float(0.0)
    wm_total = float(0.0)
    for i in range(start, end):
        w_total += weights[i]
        wm_total += weights[i] * (0.5 * (t_starts[i] + t_ends[i]) - m_first)
    w_before = float(0.0)
    wm_before = float(0.0)
    for i in range(start, end):
        w = weights[i]
        m = 0.5 * (t_starts[i] + t_ends[i]) - m_first
        w_after = w_total - w_before - w
        wm_after = wm_total - wm_before - w * m
        d = 2.0 * (m * w_before - wm_before) + 2.0 * (wm_after - m * w_after)
        grad_weights[i] = g * (d + 2.0 / 3.0 * w * (t_ends[i] - t_starts[i]))
        w_before += w
        wm_before += w * m
