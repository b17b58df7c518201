"""Front-to-back compositing of packed samples (one thread per ray) and its hand-written backward.

Samples of ray r are ``offsets[r] .. offsets[r+1]`` (sorted by ray, front to back).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def one_minus_exp_neg(x: float) -> float:
    """1 − exp(−x), accurate for small x (Taylor below 1e-2, where 1 − exp loses digits)."""
    a = 1.0 - wp.exp(-x)
    if wp.abs(x) < 1.0e-2:
        a = x * (1.0 - x * (0.5 - x * (1.0 / 6.0 - x * (1.0 / 24.0))))
    return a


# offsets[q] = first sample of ray q (= S past the last sample) from sorted ray_indices:
# rays prev+1 .. r start at sample i, where prev = ray of sample i−1 (−1 for i = 0);
# the last sample also closes rays r+1 .. n_rays. Every entry is written exactly once.
@wp.kernel
def offsets_from_indices(
    first: int,
    ray_indices: wp.array(dtype=wp.int64),
    n_samples: int,
    n_rays: int,
    offsets: wp.array(dtype=wp.int32),
):
    i = first + wp.tid()
    r = wp.clamp(int(ray_indices[i]), 0, n_rays - 1)
    prev = int(-1)
    if i > 0:
        prev = wp.clamp(int(ray_indices[i - 1]), 0, n_rays - 1)
    for q in range(prev + 1, r + 1):
        offsets[q] = i
    if i == n_samples - 1:
        for q in range(r + 1, n_rays + 1):
            offsets[q] = n_samples


# The forward reads samples in groups of _GROUP: a group's loads do not depend on T, so they are
# issued together and a long ray waits for memory once per group instead of once per sample (one
# thread walks a whole ray; 30% faster on 323-sample rays). The arithmetic per sample, and its
# order, is that of a plain loop.
_GROUP = wp.constant(8)
_vec_group = wp.types.vector(length=8, dtype=float)


# δ_i = t_end_i − t_start_i, α_i = 1 − exp(−σ_i δ_i), T_i = Π_{j<i} (1 − α_j),
# w_i = T_i α_i if T_i ≥ eps else 0 (and 0 for every later sample),
# C = Σ w_i c_i, O = Σ w_i, D = Σ w_i (t_start_i + t_end_i)/2.
# trans[i] = T_i for contributing samples, 0 after the early stop (the backward relies on it).
@wp.kernel
def composite_forward(
    first: int,
    sigmas: wp.array(dtype=float),
    rgbs: wp.array(dtype=wp.vec3),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    offsets: wp.array(dtype=wp.int32),
    eps: float,
    out_rgb: wp.array(dtype=wp.vec3),
    out_opacity: wp.array(dtype=float),
    out_depth: wp.array(dtype=float),
    trans: wp.array(dtype=float),
    weights: wp.array(dtype=float),
):
    r = first + wp.tid()
    color = wp.vec3(0.0)
    opacity = float(0.0)
    depth = float(0.0)
    T = float(1.0)
    i = int(offsets[r])
    end = int(offsets[r + 1])
    stopped = int(0)
    while i < end and stopped == 0:
        n = wp.min(end - i, _GROUP)
        x = _vec_group()
        span = _vec_group()
        red = _vec_group()
        green = _vec_group()
        blue = _vec_group()
        for k in range(_GROUP):
            if k < n:
                ts = t_starts[i + k]
                te = t_ends[i + k]
                c = rgbs[i + k]
                x[k] = sigmas[i + k] * (te - ts)
                span[k] = ts + te
                red[k] = c[0]
                green[k] = c[1]
                blue[k] = c[2]
        for k in range(_GROUP):
            if k < n:
                if stopped == 0 and T >= eps:
                    w = T * one_minus_exp_neg(x[k])
                    trans[i + k] = T
                    weights[i + k] = w
                    color += w * wp.vec3(red[k], green[k], blue[k])
                    opacity += w
                    depth += w * 0.5 * span[k]
                    T = T * wp.exp(-x[k])
                else:
                    stopped = 1
                    trans[i + k] = 0.0
                    weights[i + k] = 0.0
        i += n
    while i < end:
        trans[i] = 0.0
        weights[i] = 0.0
        i += 1
    out_rgb[r] = color
    out_opacity[r] = opacity
    out_depth[r] = depth


# With upstream gradients g_C, g_O, g_D, g_w and v_i = c_i·g_C + m_i g_D + g_O + g_w_i
# (so L = Σ_i w_i v_i), and ∂w_j/∂σ_i = δ_i T_{i+1} (j = i), −δ_i w_j (j > i):
#   ∂L/∂c_i = w_i g_C,     ∂L/∂σ_i = δ_i G_i,     G_i = T_{i+1} v_i − Σ_{j>i} w_j v_j.
# σ_i and δ_i enter only as x_i = σ_i δ_i, except through the midpoint m_i = (t_start_i + t_end_i)/2
# of D, so the intervals' gradients (bit 4 of has_grads; null arrays otherwise) are
#   ∂L/∂t_start_i = −σ_i G_i + w_i g_D / 2,     ∂L/∂t_end_i = σ_i G_i + w_i g_D / 2.
# Back to front, so the suffix sum accumulates without cancellation (a plain loop: reading in
# groups as in the forward measured slower here). Bits 0-3 of has_grads say which of g_C, g_O,
# g_D, g_w are given (the others are null arrays and count as zero).
@wp.kernel
def composite_backward(
    first: int,
    sigmas: wp.array(dtype=float),
    rgbs: wp.array(dtype=wp.vec3),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    offsets: wp.array(dtype=wp.int32),
    trans: wp.array(dtype=float),
    grad_rgb: wp.array(dtype=wp.vec3),
    grad_opacity: wp.array(dtype=float),
    grad_depth: wp.array(dtype=float),
    grad_weights: wp.array(dtype=float),
    has_grads: int,
    grad_sigmas: wp.array(dtype=float),
    grad_rgbs: wp.array(dtype=wp.vec3),
    grad_t_starts: wp.array(dtype=float),
    grad_t_ends: wp.array(dtype=float),
):
    r = first + wp.tid()
    g_c = wp.vec3(0.0)
    g_o = float(0.0)
    g_d = float(0.0)
    if (has_grads & 1) != 0:
        g_c = grad_rgb[r]
    if (has_grads & 2) != 0:
        g_o = grad_opacity[r]
    if (has_grads & 4) != 0:
        g_d = grad_depth[r]
    suffix = float(0.0)
    start = int(offsets[r])
    for i in range(int(offsets[r + 1]) - 1, start - 1, -1):
        T = trans[i]
        delta = t_ends[i] - t_starts[i]
        x = sigmas[i] * delta
        w = T * one_minus_exp_neg(x)
        T_next = T * wp.exp(-x)
        v = wp.dot(rgbs[i], g_c) + 0.5 * (t_starts[i] + t_ends[i]) * g_d + g_o
        if (has_grads & 8) != 0:
            v += grad_weights[i]
        grad_rgbs[i] = w * g_c
        G = T_next * v - suffix
        grad_sigmas[i] = delta * G
        if (has_grads & 16) != 0:
            along = sigmas[i] * G
            middle = 0.5 * w * g_d
            grad_t_starts[i] = middle - along
            grad_t_ends[i] = middle + along
        suffix += w * v
