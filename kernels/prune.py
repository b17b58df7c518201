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


# Item i < S: sample i (of ray r, k-th in it) goes to row new_offsets[r] + k when k < kept[r].
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
    kept: wp.array(dtype=wp.int32),
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
        if k < kept[r]:
            j = int(new_offsets[r]) + k
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
