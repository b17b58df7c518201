"""The grid refresh that counts density only where a training camera sees it
(``OccupancyGrid.count_seen_only``), and the lens margin of its pinhole test."""

import pytest
import torch

from ngp_warp import OccupancyGrid
from ngp_warp._reference import occupancy as occupancy_ref
from ngp_warp._reference.cameras import distort
from ngp_warp.data.cameras import pinhole_border_error
from test_occupancy import AABB, _cameras, blob_density, capture_draws, run_update

NEAR, MARGIN = 4.3, 6.0  # the cameras stand 4–5.2 from the box's centre: the near leaves some points out


def _devices():
    return ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)]


def _camera_in_the_box():
    """One camera at the box's centre looking along +x (half the box lies behind it)."""
    eye, back = torch.tensor([0.0, 0.0, 1.0]), torch.tensor([-1.0, 0.0, 0.0])  # OpenGL: it looks down -z
    up = torch.tensor([0.0, 0.0, 1.0])
    right = torch.linalg.cross(up, back)
    c2w = torch.cat([torch.stack([right, up, back], 1), eye[:, None]], 1)[None]
    return c2w, torch.tensor([[30.0, 30.0, 32.0, 24.0]]), 64, 48


def _update_in_world(grid):
    """A warm-up refresh (each cell once, from occs = 0): its cells, the world points the density
    was asked at, and those densities."""
    draws = capture_draws(grid)
    asked = []

    def density(points):
        v = blob_density(points.cpu()).to(points.device) + 0.5
        asked.append((points.cpu().clone(), v.cpu().clone()))
        return v

    assert grid.update(0, density)
    del grid._draw
    return torch.cat([c for c, _ in draws]).long().cpu(), torch.cat([p for p, _ in asked]), torch.cat([v for _, v in asked])


@pytest.mark.parametrize("device", _devices())
@pytest.mark.parametrize("cameras, near, contraction", [("around", NEAR, None), ("around", 0.0, "l2"),
                                                         ("inside", 0.2, None)])
def test_refresh_zeroes_the_density_of_points_no_camera_sees(device, cameras, near, contraction):
    torch.manual_seed(0)
    grid = OccupancyGrid(AABB, resolution=16, levels=1 if contraction else 2, contraction=contraction).to(device)
    c2w, intr, w, h = _cameras() if cameras == "around" else _camera_in_the_box()
    grid.count_seen_only(c2w, intr, w, h, near=near, margin=MARGIN)
    cells, points, values = _update_in_world(grid)
    kept = grid.occs.cpu()[cells].double()
    # points within float rounding of the near sphere or an image border may go either way
    strict = occupancy_ref.zero_unseen(points, values, c2w, intr, w - 1e-3, h - 1e-3, near + 1e-4, MARGIN - 1e-3)
    loose = occupancy_ref.zero_unseen(points, values, c2w, intr, w + 1e-3, h + 1e-3, max(near - 1e-4, 0), MARGIN + 1e-3)
    assert ((kept == 0) | (kept == loose)).all() and ((kept > 0) | (strict == 0)).all()
    torch.testing.assert_close(kept[kept > 0], values.double()[kept > 0], rtol=1e-6, atol=0)
    assert 0.1 < (kept > 0).double().mean() < 0.9  # both kinds of point are drawn
    if cameras == "inside":  # behind the camera: projected through the centre, they would land in the image
        behind = points[:, 0] < -0.05
        assert behind.sum() > 100 and (kept[behind] == 0).all()
    elif contraction is None:
        near_only = occupancy_ref.zero_unseen(points, values, c2w, intr, w + 1e6, h + 1e6, near, 0.0)
        border_only = occupancy_ref.zero_unseen(points, values, c2w, intr, w, h, 0.0, MARGIN)
        assert (near_only == 0).any() and (border_only == 0).any()  # the near and the image each leave points out
    else:  # world points far beyond the inner box
        assert points.abs().max() > 10 * AABB.abs().max()


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
    """With grid_seen_only, the trainer tests points against its training cameras
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


@pytest.mark.parametrize("lens", ["pinhole", "strong OpenCV"])
def test_no_point_a_training_ray_samples_is_zeroed(tmp_path, lens):
    """Every point of every training pixel's sub-rays, from the near to the grid's edge, is kept
    (float64 twin and kernel), and a distorted lens grows the image by 1 px plus its pinhole error."""
    from data_fixtures import colmap_scene
    from ngp_warp.data.cameras import generate_rays
    from ngp_warp.data.loading import load_scene
    from ngp_warp.data.scene import write_demo_scene
    from ngp_warp.training.trainer import Trainer
    from test_train import tiny_config

    if lens == "pinhole":
        write_demo_scene(tmp_path / "s", width=32, height=24, n_train=12, n_test=1)
    else:
        colmap_scene(tmp_path / "s", "OPENCV", params=[11.0, 10.0, 6.2, 4.9, -0.25, 0.05, 0.01, -0.008], n=10)
    cfg = tiny_config(1)
    cfg.grid_seen_only = True
    trainer = Trainer(load_scene(tmp_path / "s"), cfg, device="cpu")
    split, grid = trainer.train_split, trainer.grid
    lens_error = pinhole_border_error(split.intrinsics, split.distortion, split.width, split.height)
    assert (lens_error > 1.0) == (lens == "strong OpenCV")
    assert grid._seen_frame[3] == pytest.approx(1.0 + (lens_error if split.has_distortion else 0.0))
    offsets = torch.tensor([0.0, 1 / 6, 0.5, 5 / 6, 1 - 1e-6], dtype=torch.float64)
    k, py, px, oy, ox = (a.reshape(-1) for a in torch.meshgrid(
        *(torch.arange(n, dtype=torch.float64) for n in (len(split), split.height, split.width)), offsets, offsets,
        indexing="ij"))
    k = k.long()
    origins, dirs = generate_rays(split.c2w[k].double(), split.intrinsics[k].double(),
                                  split.distortion[k].double() if split.has_distortion else None,
                                  px + ox - 0.5, py + oy - 0.5)
    near = trainer.model.march.near
    t = torch.cat([near * (1 + torch.logspace(-6, 0, 20, dtype=torch.float64)), torch.linspace(2 * near, 20 * near, 40)])
    points = (origins[:, None] + t[None, :, None] * dirs[:, None]).reshape(-1, 3)
    c, h = grid.aabb[:3].double(), grid.aabb[3:].double()
    half = (h - c) / 2 * 2 ** (grid.levels - 1)
    points = points[((points - (c + h) / 2).abs() <= half).all(-1)]
    ones = torch.ones(points.shape[0], dtype=torch.float64)
    assert points.shape[0] > 10_000
    assert (occupancy_ref.zero_unseen(points, ones, split.c2w, split.intrinsics, *grid._seen_frame) == 1).all()
    values = ones.float()
    grid._zero_unseen(points.float().contiguous(), values)
    assert (values == 1).all()
