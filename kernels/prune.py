"""Pruning packed samples to those that composite (no gradient: the densities come from a
no-grad pass), packed into a buffer of fixed size.

Samples of ray r are ``offsets[r] .. offsets[r+1]`` (sorted by ray, front to back).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


# Samples of ray r that composite_forward blends: sample i counts while T_i ≥ eps, with
# T_0 = 1 and T_{i+1} = T_i exp(−σ_i δ_i) (the same recurrence, so the same samples).
@wp.kernel
def count_contributing(
    first: int,
    sigmas: wp.array(dtype=float),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    offsets: wp.array(dtype=wp.int32),
    eps: float,
    counts: wp.array(dtype=wp.int32),
):
    r = first + wp.tid()
    start = int(offsets[r])
    end = int(offsets[r + 1])
    i = start
    T = float(1.0)
    while i < end and T >= eps:
        T = T * wp.exp(-sigmas[i] * (t_ends[i] - t_starts[i]))
        i += 1
    counts[r] = i - start


# Rays are kept whole, in order, while their contributing samples fit: with the inclusive prefix
# sums c_r of the counts and M = the largest c_r ≤ capacity (0 if none),
#   new_offsets[0] = 0,  new_offsets[r + 1] = min(c_r, M),
#   ray_mask[r] = (c_r ≤ capacity or the ray has no contributing sample).
# (c is non-decreasing, so the rays that fit are a prefix and min(c_r, M) is their prefix sum.)
# One item per entry of new_offsets; each finds M by binary search.
@wp.kernel
def fit_rays(
    first: int,
    n_rays: int,
    capacity: int,
    inclusive: wp.array(dtype=wp.int32),
    new_offsets: wp.array(dtype=wp.int32),
    ray_mask: wp.array(dtype=wp.uint8),
):
    r = first + wp.tid()
    lo = int(0)  # M = inclusive[lo - 1]: the first lo entries are ≤ capacity
    hi = n_rays
    while lo < hi:
        mid = (lo + hi) // 2
        if int(inclusive[mid]) <= capacity:
            lo = mid + 1
        else:
            hi = mid
    m = int(0)
    before = int(0)  # c_{r-1}, 0 for r = 0
    if lo > 0:
        m = int(inclusive[lo - 1])
    if r > 0:
        before = int(inclusive[r - 1])
    new_offsets[r] = wp.min(before, m)
    if r < n_rays:
        c = int(inclusive[r])
        ray_mask[r] = wp.uint8(c <= capacity or c == before)


# Item i < S: sample i (of ray r, k-th in it) goes to row new_offsets[r] + k when k is below the
# ray's kept count new_offsets[r + 1] − new_offsets[r].
# Item i < capacity past the kept rows (new_offsets[n_rays]): a padding row, ray n_rays, an empty
# interval [0, 0] at pad_position looking along +z.
@wp.kernel
def pack_contributing(
    first: int,
    n_samples: int,
    capacity: int,
    n_rays: int,
    ray_indices: wp.array(dtype=wp.int64),
    offsets: wp.array(dtype=wp.int32),
    new_offsets: wp.array(dtype=wp.int32),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    positions: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    pad_position: wp.vec3,
    out_ray_indices: wp.array(dtype=wp.int64),
    out_t_starts: wp.array(dtype=float),
    out_t_ends: wp.array(dtype=float),
    out_positions: wp.array(dtype=wp.vec3),
    out_directions: wp.array(dtype=wp.vec3),
):
    i = first + wp.tid()
    if i < n_samples:
        r = int(ray_indices[i])
        k = i - int(offsets[r])
        start = int(new_offsets[r])
        if k < int(new_offsets[r + 1]) - start:
            j = start + k
            out_ray_indices[j] = ray_indices[i]
            out_t_starts[j] = t_starts[i]
            out_t_ends[j] = t_ends[i]
            out_positions[j] = positions[i]
            out_directions[j] = directions[i]
    if i < capacity and i >= int(new_offsets[n_rays]):
        out_ray_indices[i] = wp.int64(n_rays)
        out_t_starts[i] = 0.0
        out_t_ends[i] = 0.0
        out_positions[i] = pad_position
        out_directions[i] = wp.vec3(0.0, 0.0, 1.0)
