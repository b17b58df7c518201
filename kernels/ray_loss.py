"""The photometric loss of a batch of pixels (each the mean of k rays) over their backgrounds,
reduced over the pixels in the kernel, and its backward (one launch each instead of a few dozen
torch operations).

A thread walks ``RAYS_PER_THREAD`` pixels, a stride of the thread count apart (neighbouring
threads read neighbouring pixels), and adds its partial sums atomically, so the four shared sums
see few atomics. On the CPU the launch must stay on one thread (Warp's CPU
atomics are plain read-modify-writes).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

RAYS_PER_THREAD = 8


# ℓ(e) per channel: e² (delta ≤ 0), or Huber: e²/2 for |e| < δ, δ (|e| − δ/2) beyond
@wp.func
def channel_loss(e: float, delta: float) -> float:
    if delta <= 0.0:
        return e * e
    a = wp.abs(e)
    if a < delta:
        return 0.5 * e * e
    return delta * (a - 0.5 * delta)


# dℓ/de
@wp.func
def channel_loss_grad(e: float, delta: float) -> float:
    if delta <= 0.0:
        return 2.0 * e
    return wp.clamp(e, -delta, delta)


# A pixel p is the mean of its k rays r = p k ... p k + k − 1 (k = 1: one ray per pixel):
#   mean_r v_r, for per-ray scalars and colours
@wp.func
def pixel_mean(p: int, k: int, values: wp.array(dtype=float)) -> float:
    total = float(0.0)
    for r in range(p * k, p * k + k):
        total += values[r]
    return total / float(k)


@wp.func
def pixel_mean(p: int, k: int, values: wp.array(dtype=wp.vec3)) -> wp.vec3:
    total = wp.vec3(0.0)
    for r in range(p * k, p * k + k):
        total += values[r]
    return total / float(k)


#   e_p = mean_r rgb_r + b_p (1 − mean_r o_r) − target_p
@wp.func
def blended_error(p: int, k: int, rgb: wp.array(dtype=wp.vec3), opacity: wp.array(dtype=float),
                  background: wp.array(dtype=wp.vec3), target: wp.array(dtype=wp.vec3)) -> wp.vec3:
    return pixel_mean(p, k, rgb) + background[p] * (1.0 - pixel_mean(p, k, opacity)) - target[p]


# m_p: 1 when the mask keeps all of the pixel's rays (no mask: 1)
@wp.func
def pixel_weight(p: int, k: int, has_mask: int, mask: wp.array(dtype=wp.uint8)) -> float:
    if has_mask == 0:
        return 1.0
    m = float(1.0)
    for r in range(p * k, p * k + k):
        m = wp.min(m, float(mask[r]))
    return m


# e_p per pixel p, mask m_p ∈ {0, 1}, extra term x_p = mean_r x_r over its rays:
#   sums += [Σ m_p mean_c ℓ(e_c), Σ m_p mean_c e_c², Σ m_p x_p, Σ m_p]
@wp.kernel
def ray_loss_sums(
    first: int,
    n_pixels: int,
    k: int,
    n_threads: int,
    rgb: wp.array(dtype=wp.vec3),
    opacity: wp.array(dtype=float),
    background: wp.array(dtype=wp.vec3),
    target: wp.array(dtype=wp.vec3),
    has_mask: int,
    mask: wp.array(dtype=wp.uint8),
    has_extra: int,
    extra: wp.array(dtype=float),
    delta: float,
    sums: wp.array(dtype=float),
):
    t = first + wp.tid()
    loss = float(0.0)
    squared = float(0.0)
    extras = float(0.0)
    count = float(0.0)
    for p in range(t, n_pixels, n_threads):
        m = pixel_weight(p, k, has_mask, mask)
        e = blended_error(p, k, rgb, opacity, background, target)
        loss += m * (channel_loss(e[0], delta) + channel_loss(e[1], delta) + channel_loss(e[2], delta)) / 3.0
        squared += m * wp.dot(e, e) / 3.0
        if has_extra != 0:
            extras += m * pixel_mean(p, k, extra)
        count += m
    wp.atomic_add(sums, 0, loss)
    wp.atomic_add(sums, 1, squared)
    wp.atomic_add(sums, 2, extras)
    wp.atomic_add(sums, 3, count)


# loss = (S_ℓ + λ S_x) / max(S_m, 1),   mse = S_e² / max(S_m, 1)   (one thread)
@wp.kernel
def ray_loss_finish(first: int, extra_weight: float, sums: wp.array(dtype=float), loss: wp.array(dtype=float),
                    mse: wp.array(dtype=float)):
    rays = wp.max(sums[3], 1.0)
    loss[0] = (sums[0] + extra_weight * sums[2]) / rays
    mse[0] = sums[1] / rays


# ray r of pixel p = r div k, g_p = ∂loss · m_p / (k max(S_m, 1)):
#   ∂rgb_r = g_p ℓ'(e_p) / 3,   ∂o_r = −⟨∂rgb_r, b_p⟩,   ∂x_r = λ g_p
@wp.kernel
def ray_loss_backward(
    first: int,
    k: int,
    rgb: wp.array(dtype=wp.vec3),
    opacity: wp.array(dtype=float),
    background: wp.array(dtype=wp.vec3),
    target: wp.array(dtype=wp.vec3),
    has_mask: int,
    mask: wp.array(dtype=wp.uint8),
    has_extra: int,
    delta: float,
    extra_weight: float,
    sums: wp.array(dtype=float),
    grad_loss: wp.array(dtype=float),
    grad_rgb: wp.array(dtype=wp.vec3),
    grad_opacity: wp.array(dtype=float),
    grad_extra: wp.array(dtype=float),
):
    r = first + wp.tid()
    p = r // k
    g = grad_loss[0] * pixel_weight(p, k, has_mask, mask) / (wp.max(sums[3], 1.0) * float(k))
    e = blended_error(p, k, rgb, opacity, background, target)
    d = (g / 3.0) * wp.vec3(channel_loss_grad(e[0], delta), channel_loss_grad(e[1], delta),
                            channel_loss_grad(e[2], delta))
    grad_rgb[r] = d
    grad_opacity[r] = -wp.dot(d, background[p])
    if has_extra != 0:
        grad_extra[r] = extra_weight * g
