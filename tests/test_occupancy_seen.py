"""The grid refresh that counts density only where a training camera sees it
(``OccupancyGrid.count_seen_only``), and the lens margin of its pinhole test."""

import pytest
import torch

from ngp_warp import OccupancyGrid
from ngp_warp._reference import occupancy as occupancy_ref
from ngp_warp._reference.cameras import distort
from ngp_warp.data.cameras import pinhole_border_error
from test_occupancy import AABB, _cameras, blob_density, run_update

NEAR, MARGIN = 4.3, 6.0  # the cameras stand 4–5.2 from the box's centre: the near leaves some points out


def _devices():
    return ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)]


@pytest.mark.parametrize("device", _devices())
def test_refresh_zeroes_the_density_of_points_no_camera_sees(device):
    torch.manual_seed(0)
    grid = OccupancyGrid(AABB, resolution=16, levels=2).to(device)
    c2w, intr, w, h = _cameras()
    grid.count_seen_only(c2w, intr, w, h, near=NEAR, margin=MARGIN)
    cells, points, values = run_update(grid, 0, fn=lambda p: blob_density(p.cpu()).to(p.device) + 0.5)
    kept = grid.occs.cpu()[cells.long().cpu()].double()  # warm-up: each cell once, from occs = 0
    # points within float rounding of the near sphere or an image border may go either way
    strict = occupancy_ref.zero_unseen(points, values, c2w, intr, w - 1e-3, h - 1e-3, NEAR + 1e-4, MARGIN - 1e-3)
    loose = occupancy_ref.zero_unseen(points, values, c2w, intr, w + 1e-3, h + 1e-3, NEAR - 1e-4, MARGIN + 1e-3)
    assert ((kept == 0) | (kept == loose)).all() and ((kept > 0) | (strict == 0)).all()
    torch.testing.assert_close(kept[kept > 0], values.cpu().double()[kept > 0], rtol=1e-6, atol=0)
    assert 0.1 < (kept > 0).double().mean() < 0.9  # both kinds of point are drawn
    near_only = occupancy_ref.zero_unseen(points, values, c2w, intr, w + 1e6, h + 1e6, NEAR, 0.0)
    border_only = occupancy_ref.zero_unseen(points, values, c2w, intr, w, h, 0.0, MARGIN)
    assert (near_only == 0).any() and (border_only == 0).any()  # the near and the image each leave points out


def test_refresh_without_cameras_keeps_every_density():
    grid = OccupancyGrid(AABB, resolution=8, levels=2)
    cells, _, values = run_update(grid, 0)
    torch.testing.assert_close(grid.occs[cells.long()], values, rtol=1e-6, atol=0)


@pytest.mark.parametrize("name, value", [("near", -1.0), ("near", float("inf")), ("margin", float("nan")),
                                         ("margin", True), ("near", "1")])
def test_count_seen_only_rejects_bad_distances(name, value):
    grid = OccupancyGrid(AABB, resolution=4)
    c2w, intr, w, h = _cameras()
    with pytest.raises(ValueError, match=name):
        grid.count_seen_only(c2w, intr, w, h, **{name: value})
    with pytest.raises(ValueError, match="c2w"):
        grid.count_seen_only(c2w[:, :2], intr, w, h)


def test_pinhole_border_error_is_how_far_the_lens_moves_a_border_pixel():
    intr = torch.tensor([[300.0, 310.0, 101.0, 148.0], [280.0, 280.0, 99.0, 152.0]])
    lens = torch.tensor([[0.06, -0.08, 0.01, 0.0, -1e-3, 2e-4], [-0.1, 0.02, 0.0, 0.0, 0.0, 0.0]])
    w, h = 200, 300
    assert pinhole_border_error(intr, torch.zeros(2, 6), w, h) == 0.0
    error = pinhole_border_error(intr, lens, w, h, samples=201)
    # twin: of the rays whose pixel lies in the image, the pinhole pixels reach at most ``error``
    # beyond the image, and about that far at the worst border point
    beyond = 0.0
    for (fx, fy, cx, cy), k in zip(intr.double(), lens.double()):
        u, v = torch.meshgrid(torch.linspace(-30, w + 30, 461, dtype=torch.float64),
                              torch.linspace(-30, h + 30, 681, dtype=torch.float64), indexing="ij")
        x, y = ((u - cx) / fx).reshape(-1), ((v - cy) / fy).reshape(-1)
        xd, yd = distort(x, y, k.expand(x.numel(), 6))
        ud, vd = xd * fx + cx, yd * fy + cy
        held = (ud >= 0) & (ud <= w) & (vd >= 0) & (vd <= h)
        out = torch.maximum(torch.maximum(-u.reshape(-1), u.reshape(-1) - w), torch.maximum(-v.reshape(-1), v.reshape(-1) - h))
        beyond = max(beyond, float(out[held].max()))
    assert 1.0 < error and 0.7 * error < beyond <= error + 0.2


def test_training_refreshes_count_what_the_training_rays_can_sample(tmp_path):
    """With grid_seen_only (off by default), the trainer tests points against its training cameras
    at the march's near: a refresh from the same weights and draws keeps every density but those
    of unseen points, which it zeroes."""
    from ngp_warp.data.loading import load_scene
    from ngp_warp.data.scene import write_demo_scene
    from ngp_warp.training.trainer import Trainer
    from test_train import tiny_config

    write_demo_scene(tmp_path / "demo", width=32, height=32, n_train=12, n_test=1)
    scene = load_scene(tmp_path / "demo")
    assert not Trainer(scene, tiny_config(1), device="cpu").config.grid_seen_only
    occs = {}
    for seen_only in (True, False):
        cfg = tiny_config(1)
        cfg.grid_seen_only = seen_only
        trainer = Trainer(scene, cfg, device="cpu")
        split = trainer.train_split
        expected = (split.width, split.height, trainer.model.march.near, 1.0) if seen_only else None
        assert trainer.grid._seen_frame == expected
        trainer.step()
        occs[seen_only] = trainer.grid.occs.clone()
    zeroed = (occs[True] == 0) & (occs[False] > 0)
    assert ((occs[True] == occs[False]) | zeroed).all() and zeroed.sum() > 0
