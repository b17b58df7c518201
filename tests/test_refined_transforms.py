"""Refined training poses written back as a transforms file: it loads, its trained frames carry
the refined matrices, every other frame and key is as it was, for each kind of scene folder."""

import json

import pytest
import torch
from data_fixtures import colmap_scene, instant_ngp, nerf_synthetic

from ngp_warp.training.camera_refinement import rotation_matrices
from ngp_warp.data.loading import load_scene
from ngp_warp.training.refined_transforms import REFINED_TRANSFORMS, refined_transforms


def knocked(c2w: torch.Tensor, seed: int) -> torch.Tensor:
    """[N, 3, 4] float64: each camera turned by up to about 3° and shifted by up to 0.05."""
    g = torch.Generator().manual_seed(seed)
    omega = (torch.rand(len(c2w), 3, generator=g, dtype=torch.float64) - 0.5) * 0.1
    tau = (torch.rand(len(c2w), 3, generator=g, dtype=torch.float64) - 0.5) * 0.1
    c2w = c2w.double()
    return torch.cat([rotation_matrices(omega) @ c2w[:, :, :3], (c2w[:, :, 3] + tau)[:, :, None]], dim=-1)


def cameras_by_image(scene) -> dict:
    """image path → (c2w [3, 4], intrinsics [4]) over both splits of ``scene``."""
    return {name: (split.c2w[i], split.intrinsics[i]) for split in (scene.train, scene.test)
            for i, name in enumerate(split.names)}


def write_scene(kind: str, folder):
    if kind == "instant-ngp":
        instant_ngp(folder, n=9)  # frames 0 and 8 are held out of training
    elif kind == "nerf-synthetic":
        nerf_synthetic(folder, n_train=4)
    else:
        colmap_scene(folder, n=6)
    return load_scene(folder)


@pytest.mark.parametrize("kind", ["instant-ngp", "nerf-synthetic", "colmap"])
def test_refined_poses_reload_in_place_of_the_trained_ones(tmp_path, kind):
    scene = write_scene(kind, tmp_path / "scene")
    refined = knocked(scene.train.c2w, seed=1)
    run = tmp_path / "runs" / "run"
    run.mkdir(parents=True)
    meta = refined_transforms(tmp_path / "scene", 1, scene.train.names, refined)
    (run / REFINED_TRANSFORMS).write_text(json.dumps(meta))
    again = load_scene(run / REFINED_TRANSFORMS)

    before, after = cameras_by_image(scene), cameras_by_image(again)
    trained = dict(zip(scene.train.names, refined))
    assert set(after) == set(scene.train.names) | (set(before) if kind != "nerf-synthetic" else set())
    for name, (c2w, intrinsics) in after.items():
        expected = trained[name] if name in trained else before[name][0]
        torch.testing.assert_close(c2w.double(), expected.double(), rtol=0, atol=1e-6)
        torch.testing.assert_close(intrinsics, before[name][1])
        assert (name in trained) == (not torch.allclose(c2w, before[name][0], atol=1e-3))
    torch.testing.assert_close(again.world_from_scene, scene.world_from_scene)
    if kind != "nerf-synthetic":  # the file's own keys (box, lens) are kept
        torch.testing.assert_close(again.aabb, scene.aabb)
        assert again.train.has_distortion == scene.train.has_distortion
    assert meta["refined_from"].endswith("transforms_train.json" if kind == "nerf-synthetic" else
                                         "transforms.json" if kind == "instant-ngp" else "0")


def test_a_refined_start_pose_replaces_the_frames_start_and_end(tmp_path):
    scene = write_scene("instant-ngp", tmp_path / "scene")
    meta = json.loads((tmp_path / "scene" / "transforms.json").read_text())
    for frame in meta["frames"]:  # instant-ngp reads a start pose before transform_matrix
        frame["transform_matrix_start"] = frame["transform_matrix"]
        frame["transform_matrix_end"] = frame.pop("transform_matrix")
    (tmp_path / "scene" / "transforms.json").write_text(json.dumps(meta))
    refined = knocked(scene.train.c2w, seed=2)
    written = refined_transforms(tmp_path / "scene", 1, scene.train.names, refined)
    (tmp_path / REFINED_TRANSFORMS).write_text(json.dumps(written))
    again = cameras_by_image(load_scene(tmp_path / REFINED_TRANSFORMS))
    for name, c2w in zip(scene.train.names, refined):
        torch.testing.assert_close(again[name][0].double(), c2w, rtol=0, atol=1e-6)


def test_refuses_poses_that_do_not_fit_the_file(tmp_path):
    scene = write_scene("instant-ngp", tmp_path / "scene")
    refined = knocked(scene.train.c2w, seed=2)
    with pytest.raises(ValueError, match=r"refined_c2w must be \[7, 3, 4\]"):
        refined_transforms(tmp_path / "scene", 1, scene.train.names, refined[:6])
    with pytest.raises(ValueError, match="no frame for 1 refined image"):
        refined_transforms(tmp_path / "scene", 1, [*scene.train.names[:6], str(tmp_path / "other.png")],
                           refined)
