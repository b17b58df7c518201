"""benchmarks/ingp_captures.py: the capture scenes written as instant-ngp's users train them
(colmap2nerf's placement of the cameras, its box), and the table of instant-ngp's results."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from ngp_warp.data.loading import load_scene
from ngp_warp.data.scene import write_demo_scene

from benchmark_scripts import load_benchmark

ingp_captures = load_benchmark("ingp_captures")
capture_scenes = load_benchmark("capture_scenes")


def ring_looking_at(target, n=12, radius=3.0, height=1.0, tilt=(0.2, -0.1, 0.97)):
    """[n, 4, 4] float64 OpenGL camera-to-world on a ring about the axis ``tilt`` through
    ``target``, each looking at ``target``."""
    up = np.asarray(tilt) / np.linalg.norm(tilt)
    side = np.cross(up, [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    other = np.cross(up, side)
    poses = []
    for a in np.linspace(0, 2 * math.pi, n, endpoint=False):
        eye = target + radius * (math.cos(a) * side + math.sin(a) * other) + height * up
        back = (eye - target) / np.linalg.norm(eye - target)
        right = np.cross(up, back)
        right /= np.linalg.norm(right)
        pose = np.eye(4)
        pose[:3, :3] = np.stack([right, np.cross(back, right), back], 1)
        pose[:3, 3] = eye
        poses.append(pose)
    return np.stack(poses)


def test_the_cameras_are_placed_as_colmap2nerf_places_them():
    target = np.array([2.0, -1.0, 0.5])
    poses = ring_looking_at(target)
    np.testing.assert_allclose(ingp_captures.looked_at_point(poses), target, atol=1e-9)
    placed = ingp_captures.colmap2nerf_poses(poses)
    np.testing.assert_allclose(np.linalg.norm(placed[:, :3, 3], axis=1).mean(), 4.0)
    np.testing.assert_allclose(ingp_captures.looked_at_point(placed), 0.0, atol=1e-9)
    up = placed[:, :3, 1].sum(0)
    np.testing.assert_allclose(up / np.linalg.norm(up), [0.0, 0.0, 1.0], atol=1e-12)
    for before, after in zip(poses, placed):  # one rotation for all: the cameras keep their relative poses
        np.testing.assert_allclose(after[:3, :3] @ before[:3, :3].T, placed[0, :3, :3] @ poses[0, :3, :3].T, atol=1e-12)
    for a, b in [((0, 0, 1.0), (0, 0, 1.0)), ((0, 0, -1.0), (0, 0, 1.0)), ((1.0, 0, 0), (0, 1.0, 0)),
                 ((-1.0, 0, 0), (1.0, 0, 0)), ((0, 0.6, 0.8), (0, -0.6, -0.8))]:
        turn = ingp_captures.rotation_between(np.array(a), np.array(b))
        np.testing.assert_allclose(turn @ a, b, atol=1e-12)
        np.testing.assert_allclose(turn @ turn.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(turn) == pytest.approx(1.0)


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    return write_demo_scene(tmp_path_factory.mktemp("i") / "demo", width=16, height=16, n_train=10, n_test=2,
                            supersample=1)


def test_a_colmap_capture_becomes_a_transforms_json_with_the_same_views(demo, tmp_path):
    capture = capture_scenes.write_capture(demo, tmp_path / "colmap", "colmap")
    written = ingp_captures.write_ingp_form(capture, tmp_path / "ingp", None)
    meta = json.loads((written / "transforms.json").read_text())
    assert meta["aabb_scale"] == 32 and len(meta["frames"]) == 12 and meta["w"] == 16
    assert (written / "images" / "0000.png").read_bytes() == (capture / "images" / "0000.png").read_bytes()
    poses = np.array([frame["transform_matrix"] for frame in meta["frames"]])
    np.testing.assert_allclose(np.linalg.norm(poses[:, :3, 3], axis=1).mean(), 4.0)
    up = poses[:, :3, 1].sum(0)
    np.testing.assert_allclose(up / np.linalg.norm(up), [0.0, 0.0, 1.0], atol=1e-9)
    np.testing.assert_allclose(ingp_captures.looked_at_point(poses), 0.0, atol=1e-9)
    ours, theirs = load_scene(capture), load_scene(written)
    assert [Path(p).name for p in ours.test.names] == [Path(p).name for p in theirs.test.names] == ["0000.png", "0008.png"]
    torch.testing.assert_close(ours.train.intrinsics, theirs.train.intrinsics)
    assert torch.equal(ours.train.images, theirs.train.images)
    for a, b in ((ours.train.c2w, theirs.train.c2w), (ours.test.c2w, theirs.test.c2w)):
        rotation = lambda m: m[:, :, :3].double()  # noqa: E731
        relative_a, relative_b = rotation(a)[0].T @ rotation(a), rotation(b)[0].T @ rotation(b)
        torch.testing.assert_close(relative_a, relative_b, atol=1e-5, rtol=0)
    boxed = ingp_captures.write_ingp_form(capture, tmp_path / "ingp1", 1)
    assert json.loads((boxed / "transforms.json").read_text())["aabb_scale"] == 1


def test_the_table_has_a_row_per_result(tmp_path, capsys):
    record = {"checkpoints": [{"steps": 1200, "ms_per_step": 4.5, "eval": {
        "psnr": 30.0, "psnr_right_half": 31.0, "ssim": 0.95, "white_bg": {"psnr": 30.5}}}]}
    (tmp_path / "lego-colmap-sky-a32.json").write_text(json.dumps(record))
    (tmp_path / "demo-ngp-a1.json").write_text(json.dumps({"checkpoints": [], "error": "boom"}))
    ingp_captures.table(type("Args", (), {"out": tmp_path}))
    lines = capsys.readouterr().out.splitlines()
    assert lines[2] == "| demo-ngp | 1 | failed: boom | | | | | |"
    assert lines[3] == "| lego-colmap-sky | 32 | 30.00 | 30.50 | 31.00 | 0.9500 | 1200 | 4.50 |"
