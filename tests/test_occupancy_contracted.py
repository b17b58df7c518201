"""The occupancy grid in contracted space: updates from world densities, visibility."""

import torch

from ngp_warp import OccupancyGrid
from ngp_warp._reference import contraction as contraction_ref
from ngp_warp._reference import occupancy as occupancy_ref
from test_occupancy import _cameras, run_update

INNER = torch.tensor([-1.0, -0.5, 0.0, 1.0, 0.5, 2.0])


def test_update_evaluates_world_points_of_contracted_cells():
    """density_fn gets world points; contracting them back lands each in its drawn cell."""
    torch.manual_seed(0)
    for kind in ("l2", "linf"):
        grid = OccupancyGrid(INNER, resolution=8, contraction=kind)
        assert grid.aabb.tolist() == [-2.0] * 3 + [2.0] * 3 and torch.equal(grid.inner_aabb, INNER)
        seen = []

        def density(p):  # σ = first contracted coordinate (the twin's contraction) + 2, in (0, 4)
            seen.append(p.clone())
            return contraction_ref.contract(p, kind, INNER)[:, 0].float() + 2

        cells, drawn, values = run_update(grid, 0, fn=density)
        world = torch.cat(seen)
        assert torch.equal(cells.sort().values, torch.arange(grid.n_cells, dtype=cells.dtype))
        boxes = occupancy_ref.cell_boxes(grid.aabb, 8, 1)[cells.long()]
        y = contraction_ref.contract(world, kind, INNER)
        # inside the radius-2 ball (all of the cube for L∞; L2's cube corners beyond it are never
        # marched and come back clamped), the world points are the drawn points uncontracted
        reach = torch.linalg.vector_norm(drawn, ord=2 if kind == "l2" else float("inf"), dim=-1) < 1.999
        assert reach.float().mean() > (0.5 if kind == "l2" else 0.99)
        torch.testing.assert_close(y[reach], drawn[reach].double(), rtol=1e-4, atol=1e-4)
        tol = 1e-4
        assert ((y[reach] >= boxes[reach, 0] - tol) & (y[reach] <= boxes[reach, 1] + tol)).all()
        assert world.abs().max() > 50  # the outer cells reach far into the world
        expected = occupancy_ref.update(torch.zeros(grid.n_cells), cells, values, 0.95, 0.01)
        torch.testing.assert_close(grid.occs.double(), expected[0], rtol=1e-6, atol=1e-6)
        assert torch.equal(grid.occupied().reshape(-1), expected[2])


def test_mark_invisible_cells_uncontracts_corners():
    grid = OccupancyGrid(INNER, resolution=8, contraction="l2")
    c2w, intr, w, h = _cameras()
    grid.mark_invisible_cells(c2w, intr, w, h, near_plane=0.1)
    visible = grid.occs >= 0
    pad = torch.tensor([0.0, 0.0, 1e-3, 1e-3])
    kw = dict(contraction="l2", inner_aabb=INNER)
    inner = occupancy_ref.visible_cells(grid.aabb, 8, 1, c2w, intr - pad, w - 2e-3, h - 2e-3, 0.1, **kw)
    outer = occupancy_ref.visible_cells(grid.aabb, 8, 1, c2w, intr + pad, w + 2e-3, h + 2e-3, 0.1, **kw)
    assert (visible | ~inner).all() and (outer | ~visible).all()
    assert 0.05 < visible.float().mean() < 0.95
    plain = OccupancyGrid(torch.tensor([-2.0] * 3 + [2.0] * 3), resolution=8)
    plain.mark_invisible_cells(c2w, intr, w, h, near_plane=0.1)
    assert not torch.equal(plain.occs >= 0, visible)  # the corners did move


def test_state_dict_round_trip_keeps_the_inner_box():
    grid = OccupancyGrid(INNER, resolution=8, contraction="linf")
    other = OccupancyGrid(torch.zeros(6) + torch.tensor([-1.0] * 3 + [1.0] * 3), resolution=8, contraction="linf")
    other.load_state_dict(grid.state_dict())
    assert other.inner_aabb_host == INNER.tolist()
