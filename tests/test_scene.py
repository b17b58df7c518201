"""The procedural demo scene: Warp sphere tracer vs its float64 twin, the folder it writes."""

import json
import math

import numpy as np
import pytest
import torch

import ngp_warp.data.scene as demo
import ngp_warp.data.scene_folder as scene_folder
from ngp_warp._reference import scene as ref
from ngp_warp.data.loading import DataError, image_rays, load_scene

TINY = dict(width=16, height=12, n_train=3, n_test=2, supersample=2)


def _views(n_train=3, n_test=2, width=24, height=20, seed=1):
    train, test = demo.demo_cameras(n_train, n_test, seed)
    c2w = torch.from_numpy(np.concatenate([train, test])).float()
    f = 0.5 * width / math.tan(0.5 * demo.CAMERA_ANGLE_X)
    intr = torch.tensor([[f, f, width / 2, height / 2]]).repeat(len(c2w), 1)
    return c2w, intr


def test_kernel_matches_float64_twin():
    c2w, intr = _views()
    got = demo.render_demo_views(c2w, intr, 24, 20, supersample=2).double()
    want = ref.render_views(c2w, intr, 24, 20, 2)
    assert got.shape == want.shape == (5, 20, 24, 4)
    alpha = want[..., 3]
    assert (alpha == 0).any() and (alpha == 1).any() and ((alpha > 0) & (alpha < 1)).any()
    err = (got - want).abs().amax(-1)
    # float32 vs float64 tracing may flip a grazing sub-ray or a texel edge in a few pixels
    assert (err > 1e-3).float().mean() < 0.005
    assert err.median() < 1e-5


def test_twin_shading_is_view_dependent_and_textured():
    # same surface point seen from two directions: the Blinn-Phong highlight changes the colour
    p = torch.tensor([[0.45, 0.4, 0.6]], dtype=torch.float64)  # top of the sphere
    d1 = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64)
    d2 = torch.tensor([[0.6, 0.0, -0.8]], dtype=torch.float64)
    assert (ref.shade(p, d1) - ref.shade(p, d2)).abs().max() > 0.02
    # every object's texture takes more than one colour over its surface
    colours = ref.albedo(torch.rand(2000, 3, dtype=torch.float64) * 3 - 1.5, torch.arange(2000) % 4)
    for k in range(4):
        assert colours[k::4].std(dim=0).max() > 0.05


def test_rays_of_the_loaded_scene_hit_where_alpha_is_one(tmp_path):
    """Ties the kernel's camera convention to load_scene + image_rays: with one ray per pixel the
    alpha of a view is exactly whether the twin's tracer hits along generate_rays' rays."""
    path = demo.write_demo_scene(tmp_path / "scene", width=20, height=16, n_train=2, n_test=1, supersample=1)
    test = load_scene(path).test
    alpha = test.images[0, ..., 3].reshape(-1)
    assert set(alpha.unique().tolist()) == {0, 255}
    o, d = image_rays(test, 0)
    hit, _ = ref.trace(o.double(), d.double())
    assert (hit == (alpha == 255)).float().mean() > 0.99


def test_write_demo_scene_is_a_deterministic_nerf_synthetic_folder(tmp_path):
    a = demo.write_demo_scene(tmp_path / "a", seed=3, **TINY)
    b = demo.write_demo_scene(tmp_path / "b", seed=3, **TINY)
    c = demo.write_demo_scene(tmp_path / "c", seed=4, **TINY)
    files = sorted(p.relative_to(a).as_posix() for p in a.rglob("*") if p.is_file())
    assert files == ["scene.json", "test/r_0.png", "test/r_1.png", "train/r_0.png", "train/r_1.png",
                     "train/r_2.png", "transforms_test.json", "transforms_train.json"]
    assert all((a / f).read_bytes() == (b / f).read_bytes() for f in files)
    assert (a / "transforms_train.json").read_text() != (c / "transforms_train.json").read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b", "c"]  # no temporary folders left

    scene = load_scene(a)
    assert scene.source == "nerf-synthetic" and not scene.test_is_heldout
    assert scene.train.images.shape == (3, 12, 16, 4) and scene.test.images.shape == (2, 12, 16, 4)
    alpha = torch.cat([scene.train.images, scene.test.images])[..., 3]
    assert (alpha == 0).any() and (alpha == 255).any() and ((alpha > 0) & (alpha < 255)).any()
    # exact ground truth: re-rendering the loaded cameras reproduces the stored pixels
    again = demo.render_demo_views(scene.test.c2w, scene.test.intrinsics, 16, 12, supersample=2)
    again = (again * 255 + 0.5).clamp(0, 255).to(torch.uint8)
    assert torch.equal(again, scene.test.images)
    meta = json.loads((a / "scene.json").read_text())
    assert meta["seed"] == 3 and len(meta["objects"]) == 4


def test_demo_cameras_look_at_the_origin_and_test_views_are_new():
    train, test = demo.demo_cameras(40, 8, seed=0)
    for c2w in (train, test):
        pos = c2w[:, :, 3]
        np.testing.assert_allclose(np.linalg.norm(pos, axis=1), demo.CAMERA_RADIUS)
        np.testing.assert_allclose(c2w[:, :, 2], pos / demo.CAMERA_RADIUS, atol=1e-12)  # +z away from origin
        rot = c2w[:, :, :3]
        np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rot.shape), atol=1e-12)
        assert (pos[:, 2] > 0).all()  # upper hemisphere
    gaps = np.linalg.norm(test[:, None, :, 3] - train[None, :, :, 3], axis=-1).min(axis=1)
    assert gaps.min() > 0.05


def test_existing_folder_is_kept_unless_overwrite(tmp_path):
    out = tmp_path / "scene"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(DataError, match="already exists"):
        demo.write_demo_scene(out, **TINY)
    assert (out / "keep.txt").read_text() == "mine"
    demo.write_demo_scene(out, overwrite=True, **TINY)
    assert not (out / "keep.txt").exists() and (out / "transforms_train.json").exists()


def test_unwritable_output_is_one_line_and_leaves_nothing(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("a file, not a folder")
    with pytest.raises(DataError) as e:
        demo.write_demo_scene(blocker / "sub" / "scene", **TINY)
    assert str(blocker / "sub" / "scene") in str(e.value) and "\n" not in str(e.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_failure_mid_write_removes_everything_it_made(tmp_path, monkeypatch):
    calls = []

    def failing_imwrite(path, image):
        calls.append(path)
        if len(calls) == 3:
            raise OSError(28, "No space left on device")
        path.write_bytes(b"png")

    monkeypatch.setattr(scene_folder.iio, "imwrite", failing_imwrite)
    with pytest.raises(DataError, match="No space left on device"):
        demo.write_demo_scene(tmp_path / "new" / "deeper" / "scene", **TINY)
    assert len(calls) == 3
    assert list(tmp_path.iterdir()) == []  # the temporary folder and the parents it made are gone


def test_render_demo_views_validates():
    c2w, intr = _views(1, 1)
    for args in ((c2w[:, :2], intr, 4, 4), (c2w, intr[:1], 4, 4), (c2w.double(), intr, 4, 4), (c2w, intr, 0, 4)):
        with pytest.raises(ValueError):
            demo.render_demo_views(*args)
    with pytest.raises(ValueError):
        demo.write_demo_scene("unused", n_train=0)


@pytest.mark.cuda
def test_kernel_cuda_matches_cpu():
    c2w, intr = _views()
    cpu = demo.render_demo_views(c2w, intr, 24, 20, supersample=2)
    gpu = demo.render_demo_views(c2w.cuda(), intr.cuda(), 24, 20, supersample=2).cpu()
    err = (cpu - gpu).abs().amax(-1)
    assert (err > 1e-3).float().mean() < 0.005


def test_room_wall_radius_is_where_the_room_starts():
    """A wider room keeps a camera that the default room's wall excludes, and moves the wall's
    texture: at the same pixels the background differs while the objects stay."""
    c2w = torch.from_numpy(demo.look_at(np.array([7.0, 0.0, 1.0]))[None]).float()
    intrinsics = torch.tensor([[40.0, 40.0, 12.0, 12.0]])
    with pytest.raises(ValueError, match="inside the room"):
        demo.render_room_views(c2w, intrinsics, 24, 24)
    hall = demo.render_room_views(c2w, intrinsics, 24, 24, radius=10.0)
    assert hall.shape == (1, 24, 24, 3) and 0.0 <= float(hall.min()) and float(hall.max()) <= 1.0
    near = torch.from_numpy(demo.look_at(np.array([3.0, 0.0, 1.0]))[None]).float()
    room, wide = (demo.render_room_views(near, intrinsics, 24, 24, radius=r) for r in (demo.ROOM_RADIUS, 10.0))
    alpha = demo.render_demo_views(near, intrinsics, 24, 24)[..., 3]
    background = alpha < 1e-3
    assert background.sum() > 50
    assert (room - wide).abs()[background].mean() > 0.05
    assert torch.allclose(room[alpha > 0.999], wide[alpha > 0.999], atol=1e-6)
