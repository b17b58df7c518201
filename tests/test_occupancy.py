import pytest
import torch

from ngp_warp import OccupancyGrid
from ngp_warp._reference import occupancy as occupancy_ref

AABB = torch.tensor([-1.0, -0.5, 0.0, 1.0, 0.5, 2.0])


def blob_density(points):
    """Smooth positive density peaked at the box centre."""
    return 3.0 * torch.exp(-8.0 * ((points - torch.tensor([0.0, 0.0, 1.0])) ** 2).sum(-1))


def capture_draws(grid):
    """Wrap the grid's cell sampler to record (cells, points) of each chunk."""
    draws = []
    draw = grid._draw

    def recording(*args):
        cells, points = draw(*args)
        draws.append((cells.clone(), points.clone()))
        return cells, points

    grid._draw = recording
    return draws


def run_update(grid, step, fn=blob_density, **kw):
    """One update; returns the drawn cells, points and density values."""
    draws = capture_draws(grid)
    values = []

    def density(points):
        v = fn(points)
        values.append(v.clone())
        return v[:, None]  # [M, 1] is accepted too

    assert grid.update(step, density, **kw)
    del grid._draw
    cells = torch.cat([c for c, _ in draws])
    points = torch.cat([p for _, p in draws])
    return cells, points, torch.cat(values)


def assert_points_in_cells(grid, cells, points):
    boxes = occupancy_ref.cell_boxes(grid.aabb, grid.resolution, grid.levels)[cells.long()]
    tol = 1e-6
    assert ((points.double() >= boxes[:, 0] - tol) & (points.double() <= boxes[:, 1] + tol)).all()


def test_fresh_grid_is_fully_occupied_and_round_trips_state_dict():
    grid = OccupancyGrid(AABB, resolution=8, levels=2)
    assert grid.occupied().all() and grid.occupied().shape == (2, 8, 8, 8)
    run_update(grid, 0)
    other = OccupancyGrid(torch.zeros(6) + torch.tensor([0, 0, 0, 1, 1, 1.0]), resolution=8, levels=2)
    other.load_state_dict(grid.state_dict())
    assert torch.equal(other.bitfield, grid.bitfield) and torch.equal(other.occs, grid.occs)
    assert other.aabb_host == AABB.tolist() and "_splat" not in grid.state_dict()


def test_warmup_evaluates_every_cell_once():
    grid = OccupancyGrid(AABB, resolution=8, levels=2)
    old = grid.occs.clone()
    cells, points, values = run_update(grid, 0, chunk=300)
    assert torch.equal(cells, torch.arange(grid.n_cells, dtype=torch.int32))
    assert_points_in_cells(grid, cells, points)
    occs, thr, occupied = occupancy_ref.update(old, cells, values, 0.95, 0.01)
    torch.testing.assert_close(grid.occs.double(), occs, rtol=1e-6, atol=0)
    torch.testing.assert_close(grid.threshold.double(), thr.reshape(1), rtol=1e-6, atol=0)
    assert torch.equal(grid.occupied().reshape(-1), occupied)
    assert 0.05 < occupied.float().mean() < 0.95


def test_after_warmup_samples_uniform_and_occupied_cells_with_max_ema():
    grid = OccupancyGrid(AABB, resolution=8, levels=2)
    run_update(grid, 0, fn=lambda p: blob_density(p) * 0.01, occ_threshold=0.01)
    grid.occs.mul_(torch.rand(grid.n_cells) * 2)  # non-trivial old values (the bitfield is not repacked)
    prev_occupied = grid.occupied().reshape(-1).clone()
    old = grid.occs.clone()
    cells, points, values = run_update(grid, 512, occ_threshold=0.01, ema_decay=0.9)
    quarter = grid.n_cells // 4
    assert cells.shape == (2 * quarter,)
    assert_points_in_cells(grid, cells, points)
    uniform, from_occupied = cells[:quarter].long(), cells[quarter:].long()
    assert prev_occupied[from_occupied].all()
    assert prev_occupied[uniform].any() and not prev_occupied[uniform].all()
    assert from_occupied.unique().numel() > 0.5 * min(quarter, int(prev_occupied.sum()))
    assert cells.unique().numel() < cells.numel()  # repeated cells: scatter-max
    occs, thr, occupied = occupancy_ref.update(old, cells, values, 0.9, 0.01)
    torch.testing.assert_close(grid.occs.double(), occs, rtol=1e-6, atol=0)
    assert thr == 0.01  # the mean exceeds occ_threshold here
    assert torch.equal(grid.occupied().reshape(-1), occupied)


def test_only_every_nth_step_updates():
    grid = OccupancyGrid(AABB, resolution=4)
    calls = []
    assert not grid.update(3, lambda p: calls.append(p) or p[:, 0], every_n=4)
    assert not calls and grid.occupied().all()
    assert grid.update(8, lambda p: torch.zeros(p.shape[0]), every_n=4)
    assert not grid.occupied().any()  # threshold = min(0.01, mean 0) = 0, nothing exceeds it


def _cameras():
    eye = torch.tensor([[0.0, -4.0, 1.0], [4.0, 0.3, 1.2], [0.2, 0.1, 6.0]])
    target = torch.tensor([0.3, 0.0, 1.0])
    c2w = []
    for e in eye:
        back = torch.nn.functional.normalize(e - target, dim=0)  # OpenGL: camera looks down -z
        right = torch.nn.functional.normalize(torch.linalg.cross(torch.tensor([0.0, 0.1, 1.0]), back), dim=0)
        up = torch.linalg.cross(back, right)
        c2w.append(torch.cat([torch.stack([right, up, back], 1), e[:, None]], 1))
    intr = torch.tensor([[160.0, 160.0, 31.3, 24.7], [190.0, 190.0, 30.1, 25.2], [170.0, 170.0, 33.0, 20.0]])
    return torch.stack(c2w), intr, 64, 48


def test_mark_invisible_cells_matches_projection_reference():
    grid = OccupancyGrid(AABB, resolution=8, levels=2)
    c2w, intr, w, h = _cameras()
    grid.mark_invisible_cells(c2w, intr, w, h, near_plane=0.1)
    visible = grid.occs >= 0
    pad = torch.tensor([0.0, 0.0, 1e-3, 1e-3])
    inner = occupancy_ref.visible_cells(grid.aabb, 8, 2, c2w, intr - pad, w - 2e-3, h - 2e-3, 0.1)
    outer = occupancy_ref.visible_cells(grid.aabb, 8, 2, c2w, intr + pad, w + 2e-3, h + 2e-3, 0.1)
    assert (visible | ~inner).all() and (outer | ~visible).all()
    assert 0.1 < visible.float().mean() < 0.9
    assert torch.equal(grid.occupied().reshape(-1), visible)

    cells, _, values = run_update(grid, 0)
    assert (grid.occs[~visible] == -1).all() and not grid.occupied().reshape(-1)[~visible].any()
    mean = grid.occs[visible].mean()
    assert grid.threshold.item() == pytest.approx(min(0.01, mean.item()))


def test_single_camera_and_invalid_inputs():
    grid = OccupancyGrid(AABB, resolution=4)
    c2w, intr, w, h = _cameras()
    grid.mark_invisible_cells(c2w[0], intr[0], w, h)
    with pytest.raises(ValueError):
        grid.mark_invisible_cells(c2w[:, :2], intr, w, h)
    with pytest.raises(ValueError):
        grid.mark_invisible_cells(c2w, intr[:2], w, h)
    with pytest.raises(ValueError):
        grid.update(0, lambda p: torch.zeros(p.shape[0], 2))


def mips_twin(occupied: torch.Tensor, n_mips: int) -> torch.Tensor:
    """Pure-torch twin of the grid's mips: for m = 1 .. n_mips, the max over blocks of 2^m cells
    per axis, where the cells of cascades l ≥ 1 inside the finer cascade's box count as occupied."""
    levels, res = occupied.shape[0], occupied.shape[1]
    marks = occupied.float().clone()
    q = slice(res // 4, 3 * res // 4)
    marks[1:, q, q, q] = 1.0
    pooled = [torch.nn.functional.max_pool3d(marks[:, None], 2**m)[:, 0].reshape(levels, -1)
              for m in range(1, n_mips + 1)]
    return torch.cat([marks.new_zeros(levels, 0), *pooled], 1).reshape(-1).to(torch.uint8)


@pytest.mark.parametrize("resolution, levels, n_mips", [(16, 3, 4), (12, 2, 2), (8, 1, 3), (5, 1, 0)])
def test_mips_match_max_pool_twin(resolution, levels, n_mips):
    grid = OccupancyGrid(AABB, resolution=resolution, levels=levels)
    assert grid.n_mips == n_mips and grid.march_mips().all()  # fresh grid: everything occupied
    grid.occs.copy_((torch.rand(grid.n_cells) < 0.03).float())
    grid.threshold.fill_(0.5)
    grid._pack()
    mips = grid.march_mips()
    twin = mips_twin(grid.occupied(), n_mips)
    assert torch.equal(mips, twin)
    if n_mips >= 2:
        assert 0.05 < twin.float().mean() < 0.95  # mixed marks: the comparison is not vacuous
    # an in-place change of the bitfield (or a loaded state) is picked up before the next march
    grid.bitfield.zero_()
    assert torch.equal(grid.march_mips(), mips_twin(grid.occupied(), n_mips))
    other = OccupancyGrid(AABB, resolution=resolution, levels=levels)
    other.load_state_dict(grid.state_dict())
    assert torch.equal(other.march_mips(), grid.march_mips())


@pytest.mark.parametrize(
    "args",
    [([0, 0, 0, 1, 1], 8, 1), ([0, 0, 0, 1, -1, 1], 8, 1), ([0, 0, 0, 1, 1, 1], 6, 2), ([0, 0, 0, 1, 1, 1], 8, 0),
     ([0, 0, 0, 1, 1, 1], 0, 1), ([0, 0, 0, 1, 1, 1], 1024, 4)],
)
def test_invalid_construction_raises_value_error(args):
    aabb, resolution, levels = args
    with pytest.raises(ValueError):
        OccupancyGrid(torch.tensor(aabb, dtype=torch.float32), resolution=resolution, levels=levels)


@pytest.mark.cuda
def test_cuda_matches_cpu():
    grids = [OccupancyGrid(AABB, resolution=16, levels=2).to(d) for d in ("cpu", "cuda")]

    def update(step):
        for grid in grids:
            torch.manual_seed(step)  # same kernel seed on both devices
            grid.update(step, lambda p: blob_density(p.cpu()).to(p.device))

    update(0)
    torch.testing.assert_close(grids[0].occs, grids[1].occs.cpu(), rtol=1e-5, atol=1e-6)
    grids[1].load_state_dict(grids[0].state_dict())  # same bitfield, so the same cells are drawn
    assert torch.equal(grids[0].march_mips(), grids[1].march_mips().cpu())
    update(300)
    torch.testing.assert_close(grids[0].occs, grids[1].occs.cpu(), rtol=1e-5, atol=1e-6)
