"""Adam for hash-grid tables that leaves untouched entries alone, optionally with a running
average of the weights kept in the same pass.

tiny-cuda-nn's Adam skips the encoding's parameters whose gradient is exactly zero in a step:
an entry that no sample touched keeps its value and its moments. torch's Adam keeps moving such
an entry by its decaying first moment, which for a rarely touched fine-level entry adds about
ten more steps of size ``lr`` in the direction of the one gradient it saw.

An exponential moving average (EMA) of an entry that stands still needs no work per step: after
k steps of decays d_s towards a fixed p it is p + (a − p) Π d_s. Each entry stores the
cumulative log-decay L at which its average was last brought up to date ("synced"), so a step
touches only the entries with a gradient, and a flush brings all of them up to date.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


# torch's Adam with its bias correction folded into lr_t, eps_t:
#   m ← β1 m + (1 − β1) g,   v ← β2 v + (1 − β2) g²,   p ← p (1 − decay) − lr_t m / (√v + eps_t)
#   (decay = lr · weight_decay: AdamW's decoupled decay, on touched entries only),
#   lr_t = lr √(1 − β2^t) / (1 − β1^t),   eps_t = eps √(1 − β2^t)
@wp.func
def adam_update(p: float, g: float, m: float, v: float, lr_t: float, beta1: float, beta2: float,
                eps_t: float, decay: float):
    m = beta1 * m + (1.0 - beta1) * g
    v = beta2 * v + (1.0 - beta2) * g * g
    return p * (1.0 - decay) - lr_t * m / (wp.sqrt(v) + eps_t), m, v


# Adam on every entry with g ≠ 0; with an average (has_average ≠ 0), then its average a
# towards the new p with this step's decay d:
#   a ← p_old + (a − p_old) exp(L_before − synced)   (catch up: p stood still since the last sync)
#   a ← p_new + (a − p_new) d,   synced ← L_after = L_before + log d (both from the host)
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
    has_average: int,
    average: wp.array(dtype=float),
    synced: wp.array(dtype=float),
    log_before: float,
    log_after: float,
    average_decay: float,
):
    i = first + wp.tid()
    g = grads[i]
    if g == 0.0:
        return
    old = params[i]
    p, m, v = adam_update(old, g, exp_avg[i], exp_avg_sq[i], lr_t, beta1, beta2, eps_t, decay)
    params[i] = p
    exp_avg[i] = m
    exp_avg_sq[i] = v
    if has_average != 0:
        a = old + (average[i] - old) * wp.exp(log_before - synced[i])
        average[i] = p + (a - p) * average_decay
        synced[i] = log_after


# Bring every average up to date and rebase the log-decays to 0 (the host sets L ← 0), so that
# float32 L stays small:  a ← p + (a − p) exp(L − synced),  synced ← 0. An entry already up to
# date (synced = L) is left as it is: in float32 p + (a − p) need not round back to a, and a
# second flush (a checkpoint saved twice) must change nothing.
@wp.kernel
def flush_average(
    first: int,
    params: wp.array(dtype=float),
    average: wp.array(dtype=float),
    synced: wp.array(dtype=float),
    log_now: float,
):
    i = first + wp.tid()
    behind = log_now - synced[i]
    if behind != 0.0:
        p = params[i]
        average[i] = p + (average[i] - p) * wp.exp(behind)
    synced[i] = 0.0
