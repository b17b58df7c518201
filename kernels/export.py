"""Mesh export: which points lie in occupied cells of the occupancy grid.

A point p belongs to the finest cascade l whose box (centre c, half size h·2^l) contains it and
to the cell ijk = floor((p − (c − h·2^l)) / (2 h·2^l / R)) there (as the ray march finds it):

.. math::

    \\mathrm{occupied}(p) = \\mathrm{bit}(l, ijk) \\;\\wedge\\; |p - c| \\le h \\cdot 2^{L-1}

(points outside the coarsest cascade are empty). No gradient: export only reads the grid.
"""

import warp as wp

from ngp_warp.kernels.occupancy import box_center, box_half, cell_id, is_occupied
from ngp_warp.kernels.raymarch_funcs import grid_cell

wp.set_module_options({"enable_backward": False})


@wp.kernel
def points_occupied(
    first: int,
    points: wp.array(dtype=wp.vec3),  # [N] world (scene) positions
    aabb: wp.array(dtype=wp.float32),  # [6] the finest cascade's box
    levels: int,
    res: int,
    bitfield: wp.array(dtype=wp.uint8),  # the grid's packed occupancy bits
    occupied: wp.array(dtype=wp.uint8),  # [N] out: 1 occupied, 0 empty
):
    i = first + wp.tid()
    p = points[i]
    c = box_center(aabb)
    h = box_half(aabb)
    inv_h = wp.vec3(1.0 / h[0], 1.0 / h[1], 1.0 / h[2])
    level, ijk, lower, scale = grid_cell(p, c, h, inv_h, levels, res)
    q = p - c
    top = float(1 << (levels - 1))
    inside = wp.abs(q[0]) <= h[0] * top and wp.abs(q[1]) <= h[1] * top and wp.abs(q[2]) <= h[2] * top
    occupied[i] = wp.uint8(0)
    if inside and is_occupied(bitfield, cell_id(level, ijk, res)):
        occupied[i] = wp.uint8(1)
