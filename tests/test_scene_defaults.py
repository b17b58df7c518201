"""Per-scene defaults: the contraction key, the 360° capture test, cone steps, appearance codes."""

import dataclasses
import json
import math

import pytest
import torch

from ngp_warp.training.config import TrainConfig, resolve_defaults
from ngp_warp.data.loading import DataError, load_scene
from ngp_warp.training.scene_defaults import (FOCUS_NEAR_SHARE, appearance_dim, cameras_surround_centre, capture_near,
                                              choose_contraction, cone_steps, contraction_box, distortion_weight,
                                              focus_distance, occupancy_threshold)
from ngp_warp.data.scene_unbounded import write_unbounded_scene


def look_at(eyes, target, up=(0.0, 0.0, 1.0)):
    """[N, 3, 4] OpenGL c2w of cameras at ``eyes`` looking at ``target``."""
    out = []
    for e in eyes:
        back = torch.nn.functional.normalize(e - target, dim=0)
        right = torch.nn.functional.normalize(torch.linalg.cross(torch.tensor(up), back), dim=0)
        out.append(torch.cat([torch.stack([right, torch.linalg.cross(back, right), back], 1), e[:, None]], 1))
    return torch.stack(out)


def ring(n, arc=2 * math.pi, centre=(1.0, -2.0, 0.5)):
    a = torch.linspace(0, arc, n + 1)[:n] if arc == 2 * math.pi else torch.linspace(0, arc, n)
    c = torch.tensor(centre)
    eyes = torch.stack([4 * a.cos(), 4 * a.sin(), 1.5 + 0.3 * (3 * a).sin()], 1) + c
    return look_at(eyes, c + torch.randn(3) * 0.1)


def test_cameras_surround_centre():
    torch.manual_seed(0)
    assert cameras_surround_centre(ring(24))
    assert not cameras_surround_centre(ring(24, arc=math.pi))  # a half circle: not 360°
    assert not cameras_surround_centre(ring(6))  # too few
    eyes = torch.stack([torch.linspace(-1, 1, 20), torch.zeros(20), torch.full((20,), 4.0)], 1)
    forward_facing = look_at(eyes, torch.tensor([0.0, 0.0, -100.0]), up=(0.0, 1.0, 0.0))
    assert not cameras_surround_centre(forward_facing)
    outward = ring(24)
    outward[:, :, :3] = -outward[:, :, :3]  # the same ring looking away from the centre
    assert not cameras_surround_centre(outward)


def test_focus_distance_of_cameras_that_look_at_one_point():
    torch.manual_seed(1)
    for arc in (2 * math.pi, math.pi):  # a walk around the subject, or half of one (fox)
        c2w = ring(24, arc=arc)
        eyes, target = c2w[:, :, 3], torch.tensor([1.0, -2.0, 0.5])
        assert focus_distance(c2w) == pytest.approx(float((eyes - target).norm(dim=-1).median()), abs=0.2)
    angles = torch.linspace(0, 2 * math.pi, 26)[:25]
    radii = 2 + 7 * torch.linspace(0, 1, 25)[torch.randperm(25)] ** 2  # skewed: median 3.75, mean 4.43, least 2
    eyes = torch.stack([radii * angles.cos(), radii * angles.sin(), 0.3 * radii], 1) + target
    assert focus_distance(look_at(eyes, target)) == pytest.approx(3.75 * math.sqrt(1.09), rel=1e-5)
    assert focus_distance(ring(6)) is None  # too few
    eyes = torch.stack([torch.linspace(-1, 1, 20), torch.zeros(20), torch.full((20,), 4.0)], 1)
    assert focus_distance(look_at(eyes, torch.tensor([0.0, 0.0, -100.0]), up=(0.0, 1.0, 0.0))) is None  # parallel axes
    outward = ring(24)
    outward[:, :, :3] = -outward[:, :, :3]
    assert focus_distance(outward) is None


def test_bounded_captures_start_their_rays_a_share_of_the_way_to_the_focus(tmp_path):
    from ngp_warp.data.scene import write_demo_scene

    scene = load_scene(write_unbounded_scene(tmp_path / "u", width=8, height=8, n_train=12, n_test=2))
    focus = focus_distance(scene.train.c2w)
    assert focus is not None and FOCUS_NEAR_SHARE * focus > 1.2 * scene.near
    assert capture_near(scene, "l2") == scene.near  # contracted: the scene's own near
    assert FOCUS_NEAR_SHARE == 0.3 and capture_near(scene, None) == pytest.approx(0.3 * focus)
    assert capture_near(dataclasses.replace(scene, near=5.0), None) == 5.0  # the scene's own, where larger
    fisheye = dataclasses.replace(scene, train=dataclasses.replace(scene.train, fisheye=True))
    assert capture_near(fisheye, None) == scene.near  # a wide view may hold content closer to its camera
    assert resolve_defaults(TrainConfig(), scene, "cpu").near == scene.near
    assert resolve_defaults(TrainConfig(contraction=None), scene, "cpu").near == pytest.approx(FOCUS_NEAR_SHARE * focus)
    assert resolve_defaults(TrainConfig(contraction=None, near=0.5), scene, "cpu").near == 0.5  # asked for
    forward = look_at(torch.stack([torch.linspace(-1, 1, 12), torch.zeros(12), torch.full((12,), 4.0)], 1),
                      torch.tensor([0.0, 0.0, -100.0]), up=(0.0, 1.0, 0.0))
    facing = dataclasses.replace(scene, train=dataclasses.replace(scene.train, c2w=forward))
    assert capture_near(facing, None) == scene.near  # no point the cameras look at
    synthetic = load_scene(write_demo_scene(tmp_path / "demo", width=8, height=8, n_train=12, n_test=1))
    assert capture_near(synthetic, None) == synthetic.near


def test_unbounded_scene_asks_for_contraction_and_gets_cone_steps(tmp_path):
    scene = load_scene(write_unbounded_scene(tmp_path / "u", width=16, height=16, n_train=12, n_test=2))
    assert scene.contraction == "l2" and scene.occupancy_levels == 1
    assert choose_contraction("auto", scene) == "l2" and choose_contraction(None, scene) is None
    assert choose_contraction("linf", scene) == "linf"
    box = contraction_box(scene)
    assert (box[:3] <= scene.train.c2w[:, :, 3].amin(0)).all() and (box[3:] >= scene.train.c2w[:, :, 3].amax(0)).all()
    assert (box[:3] <= -4).all() and (box[3:] >= 4).all()
    cone, lo, hi = cone_steps(scene, "l2")
    assert cone == 1 / 256 and lo == pytest.approx(8 * math.sqrt(3) / 1024) and hi == pytest.approx(8 * math.sqrt(3))
    assert cone_steps(scene, None)[0] == 0.0 and appearance_dim(scene) == 16
    assert occupancy_threshold(scene) == 0.05  # a capture's grid, stricter than instant-ngp's 0.01
    assert resolve_defaults(TrainConfig(), scene, "cpu").occupancy_threshold == 0.05
    assert resolve_defaults(TrainConfig(occupancy_threshold=0.2), scene, "cpu").occupancy_threshold == 0.2
    # the distortion loss on bounded captures only: not this contracted scene, unless asked
    assert distortion_weight(scene, "l2") == 0.0 and distortion_weight(scene, None) == 4e-3
    assert resolve_defaults(TrainConfig(), scene, "cpu").distortion_weight == 0.0
    assert resolve_defaults(TrainConfig(contraction=None), scene, "cpu").distortion_weight == 4e-3
    assert resolve_defaults(TrainConfig(distortion_weight=0.5), scene, "cpu").distortion_weight == 0.5
    with pytest.raises(ValueError, match="contraction must be"):
        choose_contraction("sphere", scene)


def test_bad_contraction_key_is_one_line_data_error(tmp_path):
    folder = write_unbounded_scene(tmp_path / "u", width=8, height=8, n_train=3, n_test=1)
    meta = json.loads((folder / "transforms_train.json").read_text())
    meta["contraction"] = "sphere"
    (folder / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match="contraction must be one of l2, linf or null") as err:
        load_scene(folder)
    assert "\n" not in str(err.value)


def test_nerf_synthetic_scenes_get_no_distortion_loss(tmp_path):
    from ngp_warp.data.scene import write_demo_scene

    scene = load_scene(write_demo_scene(tmp_path / "demo", width=8, height=8, n_train=3, n_test=1))
    assert scene.source == "nerf-synthetic" and distortion_weight(scene, None) == 0.0
    assert resolve_defaults(TrainConfig(), scene, "cpu").distortion_weight == 0.0
