"""The unbounded 360° procedural scene: Warp tracer vs its float64 twin, the cameras, the folder."""

import json
import math

import numpy as np
import pytest
import torch

import ngp_warp.data.scene_folder as scene_folder
import ngp_warp.data.scene_unbounded as unbounded
from ngp_warp._reference import scene_unbounded as ref
from ngp_warp.data.loading import load_scene
from ngp_warp.data.data_error import DataError
from ngp_warp.kernels import scene_unbounded as K

TINY = dict(width=16, height=12, n_train=3, n_test=2, supersample=2)


def _views(n_train=3, n_test=2, width=24, height=20, seed=1):
    train, test = unbounded.unbounded_cameras(n_train, n_test, seed)
    c2w = torch.from_numpy(np.concatenate([train, test])).float()
    f = 0.5 * width / math.tan(0.5 * unbounded.CAMERA_ANGLE_X)
    return c2w, torch.tensor([[f, f, width / 2, height / 2]]).repeat(len(c2w), 1)


def _random_rays(n=3000, seed=0):
    """Rays from the train cameras' positions: a third towards the objects, the others in random
    directions, some steep, most near level (not normalised)."""
    g = torch.Generator().manual_seed(seed)
    train, _ = unbounded.unbounded_cameras(30, 1, seed)
    o = torch.from_numpy(train[:, :, 3]).float()[torch.randint(0, 30, (n,), generator=g)]
    phi = 2 * math.pi * torch.rand(n, generator=g)
    z = torch.where(torch.rand(n, generator=g) < 0.7, 0.3 * torch.rand(n, generator=g) - 0.15,
                    2 * torch.rand(n, generator=g) - 1)
    s = (1 - z * z).sqrt()
    d = torch.stack([s * torch.cos(phi), s * torch.sin(phi), z], -1)
    at_objects = torch.rand(n, 3, generator=g) * 2 - 1 - o  # a third aim at the objects' box
    return o, torch.where((torch.arange(n) % 3 == 0)[:, None], at_objects, d)


def _what(o, d, depth):
    """0 sky, 1 object, 2 ground, 3 pillar of every ray, from the twin's geometry."""
    p = o.double() + depth.double()[:, None] * d.double()
    pillar_t, _, _ = ref.pillar_hit(o.double(), d.double())
    what = torch.full_like(depth, 1, dtype=torch.long)
    what[(p[:, 2] - K.GROUND_Z).abs() < 1e-6] = 2
    what[(pillar_t - depth.double()).abs() < 1e-6 * (1 + pillar_t)] = 3
    what[depth == K.MISS] = 0
    return what


def test_rays_match_float64_twin():
    o, d = _random_rays()
    rgb, depth = unbounded.render_unbounded_rays(o, d)
    want_rgb, want_depth = ref.radiance(o.double(), torch.nn.functional.normalize(d.double(), dim=-1))
    what = _what(o, d, want_depth)
    assert all((what == k).sum() > 30 for k in range(4)), "every kind of surface is hit"
    same = (rgb.double() - want_rgb).abs().amax(-1) < 1e-4
    # float32 vs float64 may flip a grazing ray or a texel edge on a few rays
    assert same.float().mean() > 0.99
    near = (depth.double() - want_depth).abs() <= 1e-4 * want_depth.abs().clamp_min(1)
    assert near.float().mean() > 0.99
    assert ((depth == K.MISS) != (want_depth == K.MISS)).float().mean() < 0.005


def test_views_match_float64_twin():
    c2w, intr = _views()
    got = unbounded.render_unbounded_views(c2w, intr, 24, 20, supersample=2).double()
    want = ref.render_views(c2w, intr, 24, 20, 2)
    assert got.shape == want.shape == (5, 20, 24, 3)
    err = (got - want).abs().amax(-1)
    assert (err > 1e-3).float().mean() < 0.01
    assert err.median() < 1e-5
    assert want.std(dim=(0, 1, 2)).min() > 0.05  # textured, not flat


def test_far_ground_fades_to_a_well_defined_colour_and_the_background_has_structure():
    r = torch.tensor([0.5, 1.0, 2.0, 50.0, 1e3, 1e5], dtype=torch.float64)
    # points of both checker colours at each distance: the contrast falls as 1 / (1 + (r / F)^2)
    a = torch.stack([r + 0.1 * K.GROUND_CELL, torch.full_like(r, 0.1 * K.GROUND_CELL), torch.zeros_like(r)], -1)
    b = a + torch.tensor([0.0, K.GROUND_CELL, 0.0], dtype=torch.float64)
    contrast = (ref.ground_albedo(a) - ref.ground_albedo(b)).abs().amax(-1)
    assert contrast[0] > 0.3 and (contrast.diff() < 0).all() and contrast[-1] < 1e-6
    # the environment: mountains below a wavy skyline, sky above, colours vary with azimuth
    phi = torch.linspace(0, 2 * math.pi, 721, dtype=torch.float64)
    level = torch.stack([phi.cos(), phi.sin(), torch.full_like(phi, 0.05)], -1)
    level = level / level.norm(dim=-1, keepdim=True)
    env = ref.environment(level)
    assert env.std(dim=0).max() > 0.05
    up = ref.environment(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))
    assert torch.allclose(up, torch.tensor([K.SKY_ZENITH], dtype=torch.float64))
    # pillars: each its own hue
    hues = ref.pillar_albedo(torch.zeros(K.PILLAR_COUNT, 3, dtype=torch.float64), torch.arange(K.PILLAR_COUNT))
    assert torch.cdist(hues, hues).add(torch.eye(K.PILLAR_COUNT)).min() > 0.05


def test_cameras_circle_inward_at_several_heights():
    train, test = unbounded.unbounded_cameras(30, 6, seed=0)
    for c2w, heights in ((train, unbounded.TRAIN_HEIGHTS), (test, unbounded.TEST_HEIGHTS)):
        pos = c2w[:, :, 3]
        rot = c2w[:, :, :3]
        np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rot.shape), atol=1e-12)
        to_target = np.asarray(unbounded.LOOK_AT) - pos
        np.testing.assert_allclose(-c2w[:, :, 2], to_target / np.linalg.norm(to_target, axis=1, keepdims=True),
                                   atol=1e-12)
        assert sorted(set(np.round(pos[:, 2] - K.GROUND_Z, 9))) == sorted(heights)
        radius = np.linalg.norm(pos[:, :2], axis=1)
        assert (np.abs(radius / unbounded.RING_RADIUS - 1) <= 0.05 + 1e-12).all()
        assert (np.abs(pos) < unbounded.INNER_HALF).all()  # inside the inner (uncontracted) box
    azimuth = np.sort(np.arctan2(train[:, 1, 3], train[:, 0, 3]))
    assert np.diff(np.append(azimuth, azimuth[0] + 2 * math.pi)).max() < 1.0  # all the way round
    gaps = np.linalg.norm(test[:, None, :, 3] - train[None, :, :, 3], axis=-1).min(axis=1)
    assert gaps.min() > 0.2


def test_write_unbounded_scene_is_a_deterministic_loadable_folder(tmp_path):
    a = unbounded.write_unbounded_scene(tmp_path / "a", seed=3, **TINY)
    b = unbounded.write_unbounded_scene(tmp_path / "b", seed=3, **TINY)
    c = unbounded.write_unbounded_scene(tmp_path / "c", seed=4, **TINY)
    files = sorted(p.relative_to(a).as_posix() for p in a.rglob("*") if p.is_file())
    assert files == ["scene.json", "test/r_0.png", "test/r_1.png", "train/r_0.png", "train/r_1.png",
                     "train/r_2.png", "transforms_test.json", "transforms_train.json"]
    assert all((a / f).read_bytes() == (b / f).read_bytes() for f in files)
    assert (a / "transforms_train.json").read_text() != (c / "transforms_train.json").read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b", "c"]
    for split in ("train", "test"):
        meta = json.loads((a / f"transforms_{split}.json").read_text())
        assert meta["contraction"] == "l2" and meta["aabb"] == [[-4.0] * 3, [4.0] * 3]

    scene = load_scene(a)
    assert scene.train.images.shape == (3, 12, 16, 3) and scene.test.images.shape == (2, 12, 16, 3)
    assert torch.equal(scene.aabb, torch.tensor([-4.0, -4, -4, 4, 4, 4]))
    # exact ground truth: re-rendering the loaded cameras reproduces the stored pixels
    again = unbounded.render_unbounded_views(scene.test.c2w, scene.test.intrinsics, 16, 12, supersample=2)
    assert torch.equal((again * 255 + 0.5).clamp(0, 255).to(torch.uint8), scene.test.images)
    assert json.loads((a / "scene.json").read_text())["seed"] == 3


def test_existing_folder_is_kept_and_failures_leave_nothing(tmp_path, monkeypatch):
    out = tmp_path / "scene"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(DataError, match="already exists"):
        unbounded.write_unbounded_scene(out, **TINY)
    assert (out / "keep.txt").read_text() == "mine"
    calls = []

    def failing_imwrite(path, image):
        calls.append(path)
        if len(calls) == 2:
            raise OSError(28, "No space left on device")
        path.write_bytes(b"png")

    monkeypatch.setattr(scene_folder.iio, "imwrite", failing_imwrite)
    with pytest.raises(DataError, match="No space left on device") as e:
        unbounded.write_unbounded_scene(tmp_path / "new" / "deeper" / "scene", **TINY)
    assert "\n" not in str(e.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]  # no temporary folder, no parents
    calls.clear()
    with pytest.raises(DataError, match="No space left on device"):
        unbounded.write_unbounded_scene(out, overwrite=True, **TINY)
    assert (out / "keep.txt").read_text() == "mine"  # a failed overwrite keeps the old folder


def test_inputs_are_validated():
    c2w, intr = _views(1, 1)
    for args in ((c2w[:, :2], intr, 4, 4), (c2w, intr[:1], 4, 4), (c2w.double(), intr, 4, 4), (c2w, intr, 0, 4)):
        with pytest.raises(ValueError):
            unbounded.render_unbounded_views(*args)
    with pytest.raises(ValueError):
        unbounded.render_unbounded_rays(torch.zeros(3, 3), torch.zeros(2, 3))
    with pytest.raises(ValueError):
        unbounded.write_unbounded_scene("unused", n_train=0)


@pytest.mark.cuda
def test_kernel_cuda_matches_cpu():
    c2w, intr = _views()
    cpu = unbounded.render_unbounded_views(c2w, intr, 24, 20, supersample=2)
    gpu = unbounded.render_unbounded_views(c2w.cuda(), intr.cuda(), 24, 20, supersample=2).cpu()
    assert ((cpu - gpu).abs().amax(-1) > 1e-3).float().mean() < 0.01
