"""benchmarks/inner_density.py's shares of a contracted grid inside the inner box, on a hand-made grid."""

import importlib.util
from pathlib import Path

import torch

from ngp_warp.ops.occupancy import OccupancyGrid

_spec = importlib.util.spec_from_file_location("inner_density",
                                               Path(__file__).parents[1] / "benchmarks" / "inner_density.py")
inner_density = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(inner_density)


def test_inside_shares_count_the_cells_whose_centre_lies_in_the_inner_box():
    r = 8  # cells of 0.5 over [-2, 2]: indices 2..5 per axis lie inside [-1, 1]
    grid = OccupancyGrid(torch.tensor([-1.0, -1, -1, 1, 1, 1]), resolution=r, contraction="l2")
    occs = torch.full((r ** 3,), -1.0)
    bits = torch.zeros(r ** 3, dtype=torch.bool)

    def cell(i, j, k, density, occupied):
        index = (i * r + j) * r + k
        occs[index], bits[index] = density, occupied

    cell(2, 2, 2, 3.0, True)    # inside
    cell(5, 3, 4, 1.0, False)   # inside, not occupied
    cell(6, 3, 3, 4.0, True)    # outside (x centre 1.25)
    cell(0, 7, 0, 0.0, True)    # outside, no density
    packed = torch.zeros(r ** 3 // 8, dtype=torch.uint8)
    for index in torch.nonzero(bits).flatten().tolist():
        packed[index >> 3] |= 1 << (index & 7)
    grid.occs.copy_(occs)
    grid.bitfield.copy_(packed)
    density, cells = inner_density.inside_shares(grid)
    assert abs(density - 4.0 / 8.0) < 1e-6
    assert abs(cells - 1.0 / 3.0) < 1e-6
