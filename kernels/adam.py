"""Adam for hash-grid tables that leaves untouched entries alone.

tiny-cuda-nn's Adam skips the encoding's parameters whose gradient is exactly zero in a step:
an entry that no sample touched keeps its value and its moments. torch's Adam keeps moving such
an entry by its decaying first moment, which for a rarely touched fine-level entry adds about
ten more steps of size ``lr`` in the direction of the one gradient it saw.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


# For every entry with g ≠ 0 (torch's Adam with its bias correction folded into lr_t, eps_t):
#   m ← β1 m + (1 − β1) g,   v ← β2 v + (1 − β2) g²,   p ← p − lr_t m / (√v + eps_t) − decay p
#   (decay = lr · weight_decay: AdamW's decoupled decay, on touched entries only),
#   lr_t = lr √(1 − β2^t) / (1 − β1^t),   eps_t = eps √(1 − β2^t)
@wp.kernel
def lazy_adam_step(
    first: int,
    params: wp.array(dtype=float),
    grads: wp.array(dtype=float),
    exp_avg: wp.array(dtype=float),
    exp_avg_sq: wp.array(dtype=float),
    lr_t: float,
    beta1: float,
    beta2: float,
    eps_t: float,
    decay: float,
):
    i = first + wp.tid()
    g = grads[i]
    if g == 0.0:
        return
    m = beta1 * exp_avg[i] + (1.0 - beta1) * g
    v = beta2 * exp_avg_sq[i] + (1.0 - beta2) * g * g
    exp_avg[i] = m
    exp_avg_sq[i] = v
    params[i] = params[i] * (1.0 - decay) - lr_t * m / (wp.sqrt(v) + eps_t)
