"""nerfstudio camera paths made on a nerfstudio training: mapped back from the frame nerfstudio
trained in (its ``dataparser_transforms.json``, which also holds the scene file's
``applied_transform`` and ``applied_scale``) to the scene file's own, as nerfstudio's
``transform_poses_to_original_space`` maps them."""

import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from ngp_warp.data.scene import look_at
from ngp_warp.outputs import video_out
from ngp_warp.outputs.camera_path import load_camera_path
from ngp_warp.outputs.nerfstudio_frame import NERFSTUDIO_COLMAP_APPLIED, from_dataparser_frame

WORLD = torch.from_numpy(np.stack([look_at(np.array(p)) for p in [[3.0, 1, 1], [1, 3, 2], [-2, 2, 1.5]]]))


def _rigid(seed: int) -> torch.Tensor:
    """[3, 4] float64: a proper rotation and a translation."""
    g = torch.Generator().manual_seed(seed)
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))[None]
    q = q * torch.det(q)
    return torch.cat([q, torch.randn(3, 1, generator=g, dtype=torch.float64)], 1)


def to_nerfstudio(c2w: torch.Tensor, transform: torch.Tensor, scale: float) -> torch.Tensor:
    """What nerfstudio's dataparser does to a pose ([N, 3, 4]): the 4 × 4 transform applied, then
    the positions scaled."""
    pose = torch.cat([c2w.double(), torch.tensor([[[0.0, 0, 0, 1]]], dtype=torch.float64).expand(len(c2w), 1, 4)], 1)
    moved = torch.cat([transform, torch.tensor([[0.0, 0, 0, 1]], dtype=torch.float64)]) @ pose
    moved[:, :3, 3] *= scale
    return moved[:, :3]


def write_nerfstudio_path(folder, c2w: torch.Tensor) -> None:
    frames = [{"camera_to_world": torch.cat([m, torch.tensor([[0, 0, 0, 1.0]], dtype=m.dtype)]).reshape(-1).tolist(),
               "fov": 50.0, "aspect": 1.5} for m in c2w]
    (folder / "camera_path.json").write_text(json.dumps({"camera_type": "perspective", "render_height": 40,
                                                         "render_width": 60, "fps": 12, "camera_path": frames}))


def test_a_path_in_nerfstudios_frame_comes_back_to_the_scenes(tmp_path):
    transform, scale = _rigid(3), 0.37
    trained = to_nerfstudio(WORLD, transform, scale)
    write_nerfstudio_path(tmp_path, trained)
    (tmp_path / "dataparser_transforms.json").write_text(json.dumps({"transform": transform.tolist(), "scale": scale}))
    path = load_camera_path(tmp_path / "camera_path.json", 8, 8, 99, 5.0,
                            dataparser=tmp_path / "dataparser_transforms.json")
    torch.testing.assert_close(path.c2w, WORLD.float(), rtol=0, atol=1e-5)
    unmapped = load_camera_path(tmp_path / "camera_path.json", 8, 8, 99, 5.0)
    assert not torch.allclose(unmapped.c2w, WORLD.float(), atol=1e-2)  # the map matters
    # nerfstudio's transform_poses_to_original_space, transcribed: positions / scale, then the inverse 4 × 4
    pose = torch.cat([trained, torch.tensor([[[0.0, 0, 0, 1]]], dtype=torch.float64).expand(3, 1, 4)], 1)
    pose[:, :3, 3] /= scale
    inverse = torch.linalg.inv(torch.cat([transform, torch.tensor([[0.0, 0, 0, 1]], dtype=torch.float64)]))
    torch.testing.assert_close(from_dataparser_frame(trained, transform, scale), (inverse @ pose)[:, :3])


@pytest.mark.parametrize("applied, colmap_folder", [("key", False), (None, True), (None, False)])
def test_the_scene_files_applied_transform_is_taken_out(tmp_path, applied, colmap_folder):
    """nerfstudio saves transform · A and scale · applied_scale, A the file's applied_transform
    (nerfstudio's old COLMAP default beside colmap/sparse/0 without the key, else none)."""
    auto, scale, applied_scale = _rigid(4), 0.6, 2.5
    a = _rigid(5) if applied == "key" else torch.tensor(NERFSTUDIO_COLMAP_APPLIED, dtype=torch.float64)
    if applied is None and not colmap_folder:
        a = torch.eye(4, dtype=torch.float64)[:3]
    scene = tmp_path / "scene"
    (scene / "colmap" / "sparse" / "0").mkdir(parents=True) if colmap_folder else scene.mkdir()
    meta = {"frames": [], "applied_scale": applied_scale, **({"applied_transform": a.tolist()} if applied else {})}
    (scene / "transforms.json").write_text(json.dumps(meta))
    write_nerfstudio_path(tmp_path, to_nerfstudio(WORLD, auto, scale))  # the scene file's poses, as trained
    saved = torch.cat([auto, torch.tensor([[0.0, 0, 0, 1]], dtype=torch.float64)]) @ \
        torch.cat([a, torch.tensor([[0.0, 0, 0, 1]], dtype=torch.float64)])
    (tmp_path / "d.json").write_text(json.dumps({"transform": saved[:3].tolist(), "scale": scale * applied_scale}))
    path = load_camera_path(tmp_path / "camera_path.json", 8, 8, 4, 5.0, dataparser=tmp_path / "d.json", scene=scene)
    torch.testing.assert_close(path.c2w, WORLD.float(), rtol=0, atol=1e-5)
    if applied or colmap_folder:  # without the scene, the path lands elsewhere
        off = load_camera_path(tmp_path / "camera_path.json", 8, 8, 4, 5.0, dataparser=tmp_path / "d.json")
        assert not torch.allclose(off.c2w, WORLD.float(), atol=1e-2)


@pytest.mark.parametrize("content, message", [
    ({"scale": 1.0}, "not a nerfstudio dataparser_transforms.json"),
    ({"transform": [[1, 0, 0, 0], [0, 1, 0, 0]], "scale": 1.0}, "3 rows of 4 finite numbers"),
    ({"transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], "scale": 0.0}, "scale a positive number"),
    ({"transform": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], "scale": 1.0}, "not a rotation and a translation"),
    ({"transform": [[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], "scale": 1.0}, "not a rotation and a translation"),
])
def test_bad_dataparser_files_are_one_line_errors(tmp_path, content, message):
    write_nerfstudio_path(tmp_path, WORLD)
    (tmp_path / "d.json").write_text(json.dumps(content))
    with pytest.raises(ValueError, match=message) as e:
        load_camera_path(tmp_path / "camera_path.json", 8, 8, 4, 5.0, dataparser=tmp_path / "d.json")
    assert "\n" not in str(e.value)


def test_only_nerfstudio_paths_on_transforms_scenes_take_it(tmp_path):
    (tmp_path / "base_cam.json").write_text(json.dumps({"path": [{"R": [0, 0, 0, 1], "T": [0, 0, 0], "fov": 40}]}))
    (tmp_path / "d.json").write_text(json.dumps({"transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], "scale": 1}))
    with pytest.raises(ValueError, match="maps nerfstudio camera paths only"):
        load_camera_path(tmp_path / "base_cam.json", 8, 8, 4, 5.0, dataparser=tmp_path / "d.json")
    write_nerfstudio_path(tmp_path, WORLD)
    train = SimpleNamespace(width=16, height=12)
    args = SimpleNamespace(path=str(tmp_path / "camera_path.json"), frames=7, fps=9.0,
                           dataparser_transforms=str(tmp_path / "d.json"))
    with pytest.raises(ValueError, match="read from a COLMAP model"):
        video_out.camera_path_from_args(args, SimpleNamespace(train=train, source="colmap"), tmp_path)
    path = video_out.camera_path_from_args(args, SimpleNamespace(train=train, source="instant-ngp"), tmp_path)
    torch.testing.assert_close(path.c2w, WORLD.float(), rtol=0, atol=1e-6)  # the identity map
