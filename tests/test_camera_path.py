"""Camera paths (nerfstudio and instant-ngp files, orbit, spiral, the spline) and video output."""

import json
import math
from types import SimpleNamespace

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from ngp_warp.outputs import video_out
from ngp_warp.outputs.camera_path import (around_cameras, catmull_rom, load_camera_path, matrix_from_quat,
                                  ngp_to_world, ngp_transform, orbit_cameras, quat_from_matrix, slerp,
                                  spiral_cameras)
from ngp_warp.data.scene import look_at


def random_rotations(n: int) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(n, 3, 3, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r, dim1=-2, dim2=-1))[:, None, :]
    return q * torch.det(q)[:, None, None]  # proper rotations


def ngp_from_world(c2w: torch.Tensor, scale: float, offset) -> torch.Tensor:
    """instant-ngp's nerf_matrix_to_ngp, written out as its source does it (columns 1, 2 negated,
    t·scale + offset, then rows cycled so that row 0 ← row 1, row 1 ← row 2, row 2 ← row 0)."""
    m = c2w.double().clone()
    m[:, :, 1:3] *= -1
    m[:, :, 3] = m[:, :, 3] * scale + torch.tensor(offset, dtype=torch.float64)
    return m[:, [1, 2, 0]]


def quat_xyzw(r: torch.Tensor) -> list[float]:
    """The textbook trace formula (for rotations with trace > -1), x y z w as tiny-cuda-nn's JSON."""
    w = math.sqrt(1 + float(r[0, 0] + r[1, 1] + r[2, 2])) / 2
    return [float(r[2, 1] - r[1, 2]) / (4 * w), float(r[0, 2] - r[2, 0]) / (4 * w), float(r[1, 0] - r[0, 1]) / (4 * w), w]


def test_quaternions_round_trip_every_rotation():
    r = random_rotations(500)
    r[0] = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))  # 180° turns: w = 0
    r[1] = torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=torch.float64))
    q = quat_from_matrix(r)
    assert torch.allclose(q.norm(dim=-1), torch.ones(500, dtype=torch.float64))
    assert torch.allclose(matrix_from_quat(q), r, atol=1e-12)
    for k in range(2, 40):
        assert torch.allclose(torch.tensor(quat_xyzw(r[k]), dtype=torch.float64) * torch.sign(q[k, 3]), q[k], atol=1e-9)


def test_slerp_turns_at_constant_speed():
    q0, q1 = quat_from_matrix(random_rotations(2)).unbind(0)
    t = torch.linspace(-0.5, 1.5, 21, dtype=torch.float64)
    q = slerp(q0.expand(21, 4), q1.expand(21, 4), t)
    angle = lambda a, b: 2 * torch.acos((a * b).sum(-1).abs().clamp(max=1))  # noqa: E731
    total = angle(q0, q1)
    assert torch.allclose(angle(q, q0.expand(21, 4)), (t.abs() * total), atol=1e-6)
    assert torch.allclose(q[10], slerp(q0, q1, torch.tensor(0.5, dtype=torch.float64)))


def test_catmull_rom_passes_through_keys_smoothly():
    k, m = 5, 8
    quats = quat_from_matrix(random_rotations(k))
    positions = torch.randn(k, 3, dtype=torch.float64)
    fovs = torch.rand(k, dtype=torch.float64) * 40 + 30
    q, p, f = catmull_rom(quats, positions, fovs, (k - 1) * m + 1)
    keys = slice(0, None, m)
    assert torch.allclose(p[keys], positions) and torch.allclose(f[keys], fovs)
    assert torch.allclose(matrix_from_quat(q[keys]), matrix_from_quat(quats), atol=1e-9)
    m = 400  # Catmull-Rom's velocity at key i is (p[i + 1] - p[i - 1]) / 2, from either side
    _, p, _ = catmull_rom(quats, positions, fovs, (k - 1) * m + 1)
    tangent = (positions[3] - positions[1]) / 2
    assert torch.allclose((p[2 * m] - p[2 * m - 1]) * m, tangent, atol=0.02 * tangent.norm())
    assert torch.allclose((p[2 * m + 1] - p[2 * m]) * m, tangent, atol=0.02 * tangent.norm())
    line = torch.arange(k, dtype=torch.float64)[:, None] * torch.tensor([1.0, 2.0, -1.0], dtype=torch.float64)
    _, p, _ = catmull_rom(quats, line, fovs, 33)  # equally spaced keys on a line: uniform motion
    uniform = torch.linspace(0, k - 1, 33, dtype=torch.float64)[:, None] * line[1]
    assert torch.allclose(p[8:25], uniform[8:25], atol=1e-12)  # between the inner keys
    assert not torch.allclose(p[1], uniform[1])  # the repeated end keys ease in
    _, p, _ = catmull_rom(quats, positions, fovs, 10, loop=True)
    assert torch.allclose(p[0], positions[0]) and torch.allclose(p[2], positions[1])


def test_instant_ngp_base_cam_maps_back_to_world(tmp_path):
    world = torch.from_numpy(np.stack([look_at(np.array(p)) for p in [[3.0, 1, 1], [1, 3, 2], [-2, 2, 1.5], [0, -3, 2]]]))
    scale, offset = 0.2, [0.5, 0.4, 0.6]
    ngp = ngp_from_world(world, scale, offset)
    keys = [{"R": quat_xyzw(m[:, :3]), "T": m[:, 3].tolist(), "fov": 40.0 + i, "slice": 0.0, "scale": 1.0,
             "aperture_size": 0.0} for i, m in enumerate(ngp)]
    (tmp_path / "base_cam.json").write_text(json.dumps({"loop": False, "time": 0.0, "path": keys}))
    (tmp_path / "transforms.json").write_text(json.dumps({"scale": scale, "offset": offset, "frames": []}))
    s, o = ngp_transform(tmp_path)
    path = load_camera_path(tmp_path / "base_cam.json", 64, 48, 4, 25.0, s, o)
    assert torch.allclose(path.c2w.double(), world, atol=1e-5)
    fy = 0.5 * 48 / math.tan(math.radians(41.0) / 2)
    assert torch.allclose(path.intrinsics[1], torch.tensor([fy, fy, 32.0, 24.0]))
    assert (path.width, path.height, path.fps) == (64, 48, 25.0)
    assert len(load_camera_path(tmp_path / "base_cam.json", 64, 48, 30, 25.0, s, o).c2w) == 30
    assert ngp_transform(tmp_path / "nowhere") == (0.33, [0.5, 0.5, 0.5])
    assert ngp_transform(tmp_path / "transforms.json") == (scale, offset)  # the scene given as its file


def test_instant_ngp_map_of_a_path_is_the_one_training_reads(tmp_path):
    """A scene's ``aabb`` (or a scalar ``offset``) sets the unit-cube map for paths as for training."""
    (tmp_path / "transforms.json").write_text(json.dumps({"aabb": [[-10, -10, -10], [10, 10, 10]], "frames": []}))
    scale, offset = ngp_transform(tmp_path)
    assert scale == pytest.approx(0.05) and offset == pytest.approx([0.5, 0.5, 0.5])
    position = ngp_to_world(torch.eye(3)[None], torch.tensor([[0.5, 0.5, 1.0]]), scale, offset)[1]
    assert torch.allclose(position, torch.tensor([[10.0, 0.0, 0.0]], dtype=torch.float64))  # rows cycled
    (tmp_path / "transforms.json").write_text(json.dumps({"scale": 0.5, "offset": 0.25, "frames": []}))
    assert ngp_transform(tmp_path) == (0.5, [0.25, 0.25, 0.25])


def test_nerfstudio_camera_path(tmp_path):
    world = torch.from_numpy(np.stack([look_at(np.array(p)) for p in [[3.0, 1, 1], [1, 3, 2], [-2, 2, 1.5]]]))
    frames = [{"camera_to_world": torch.cat([m, torch.tensor([[0, 0, 0, 1.0]])]).reshape(-1).tolist(),
               "fov": 50.0, "aspect": 1.5} for m in world]
    (tmp_path / "camera_path.json").write_text(json.dumps({"camera_type": "perspective", "render_height": 40,
                                                           "render_width": 60, "fps": 12, "seconds": 0.25,
                                                           "camera_path": frames}))
    path = load_camera_path(tmp_path / "camera_path.json", 8, 8, 99, 5.0)
    assert torch.allclose(path.c2w, world.float())
    assert (path.width, path.height, path.fps) == (60, 40, 12.0)
    fy = 20 / math.tan(math.radians(25.0))
    assert torch.allclose(path.intrinsics, torch.tensor([fy, fy, 30.0, 20.0]).expand(3, 4))


@pytest.mark.parametrize("text, message", [
    ("{", "not valid JSON"), ('{"frames": []}', "neither a nerfstudio"), ('{"camera_path": []}', "non-empty"),
    ('{"camera_path": [{"fov": 50}], "render_height": 9}', "not a nerfstudio camera path"),
    ('{"path": [{"R": [0, 0, 0, 0], "T": [0, 0, 0], "fov": 40}]}', "not all 0"),
    ('{"path": [{"R": [0, 0, 0, 1], "T": [0, 0, 0], "fov": 190}]}', "fov"),
    ('{"camera_type": "equirectangular", "camera_path": [{"fov": 50}]}', "camera_type 'equirectangular': only perspective"),
    ('{"camera_type": "fisheye", "camera_path": [{"fov": 50}]}', "camera_type 'fisheye': only perspective"),
    ('{"render_height": 9, "camera_path": [{"fov": 50, "aspect": 1, "camera_to_world": '
     '[2, 0, 0, 0, 0, 2, 0, 0, 0, 0, 2, 0, 0, 0, 0, 1]}]}', "camera 0's camera_to_world is not a rigid camera pose"),
    ('{"render_height": 9, "camera_path": [{"fov": 50, "aspect": 1, "camera_to_world": '
     '[1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 1, 1]}]}', "camera 0's camera_to_world is not a rigid camera pose"),
])
def test_bad_path_files_are_one_line_errors(tmp_path, text, message):
    (tmp_path / "p.json").write_text(text)
    with pytest.raises(ValueError, match=message) as e:
        load_camera_path(tmp_path / "p.json", 8, 8, 4, 5.0)
    assert "\n" not in str(e.value)


def training_cameras(n: int = 30) -> torch.Tensor:
    gen = np.random.default_rng(1)
    az, el = gen.uniform(0, 2 * math.pi, n), gen.uniform(0.2, 1.2, n)
    r = gen.uniform(3.5, 4.5, n)
    pos = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], -1) + [0.2, 0.0, 0.1]
    return torch.from_numpy(np.stack([look_at(p, target=(0.2, 0.0, 0.1)) for p in pos])).float()


@pytest.mark.parametrize("make", [orbit_cameras, spiral_cameras])
def test_orbit_and_spiral_look_at_the_centre(make):
    c2w, center = training_cameras(), torch.tensor([0.2, 0.0, 0.1])
    cams = make(c2w, center, 48)
    assert cams.shape == (48, 3, 4) and cams.dtype == torch.float32
    to_center = torch.nn.functional.normalize(center - cams[:, :, 3], dim=-1)
    assert torch.allclose(-cams[:, :, 2], to_center, atol=1e-5)  # looking down -z at the centre
    rot = cams[:, :, :3].double()
    assert torch.allclose(rot.transpose(1, 2) @ rot, torch.eye(3, dtype=torch.float64).expand(48, 3, 3), atol=1e-5)
    up = torch.nn.functional.normalize(c2w[:, :, 1].mean(0), dim=0)  # the cameras' mean up axis
    height = (cams[:, :, 3] - center) @ up
    distance = (cams[:, :, 3] - center).norm(dim=-1)
    if make is orbit_cameras:
        assert torch.allclose(cams[0, :, 3], c2w[0, :, 3], atol=1e-5)
        assert torch.allclose(distance, distance[0].expand(48), atol=1e-5) and height.std() < 1e-5
    else:
        assert torch.allclose(distance, (c2w[:, :, 3] - center).norm(dim=-1).median().expand(48), atol=1e-4)
        assert height.max() - height.min() > 1.0  # the elevation swings
        step = (cams[1:, :, 3] - cams[:-1, :, 3]).norm(dim=-1)
        assert (cams[0, :, 3] - cams[-1, :, 3]).norm() < 1.5 * step.max()  # closes the loop


def test_video_files_mp4_gif_and_depth(tmp_path, monkeypatch):
    cams = around_cameras("orbit", training_cameras(), torch.tensor([[20.0, 20.0, 8.0, 6.0]]), 16, 12,
                          torch.zeros(3), 5, 10.0)

    def render_frame(c2w, intrinsics, w, h):
        assert c2w.shape == (3, 4) and intrinsics.shape == (4,) and (w, h) == (16, 12)
        depth = torch.linspace(1, 3, w * h).reshape(h, w) * c2w[0, 3].abs()
        return {"rgb": torch.rand(h, w, 3), "depth": depth, "opacity": torch.ones(h, w)}

    ext = ".mp4" if video_out.mp4_available() else ".gif"  # imageio-ffmpeg comes with the viewer extra
    written = video_out.render_path_video(render_frame, cams, tmp_path / "v.mp4", depth=True, show_progress=False)
    assert written == [tmp_path / f"v{ext}", tmp_path / f"v_depth{ext}"]
    assert iio.imread(written[0], index=None).shape[:3] == (5, 12, 16)
    depth = iio.imread(written[1], index=None)
    assert depth[:, 1, 1, 0].astype(int).mean() > depth[:, -2, -2, 0].astype(int).mean() + 100  # near is bright
    monkeypatch.setattr(video_out, "mp4_available", lambda: False)
    written = video_out.render_path_video(render_frame, cams, tmp_path / "w.mp4", show_progress=False)
    assert written == [tmp_path / "w.gif"] and iio.imread(written[0], index=None).shape == (5, 12, 16, 3)
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"v{ext}", f"v_depth{ext}", "w.gif"]


@pytest.mark.skipif(not video_out.mp4_available(), reason="needs imageio-ffmpeg (the viewer or process extra)")
def test_an_odd_sized_mp4_repeats_its_last_row_and_column(tmp_path, caplog):
    frames = np.zeros((3, 25, 31, 3), dtype=np.uint8)
    frames[:, :, :15] = 200  # left half bright, right half dark: a resample would blur the edge column
    written = video_out.write_video(frames, tmp_path / "odd.mp4", 10.0)
    read = iio.imread(written, index=None)
    assert read.shape == (3, 26, 32, 3) and not caplog.messages  # no writer warning about resizing
    assert np.abs(read[:, :, 20:].astype(int)).max() < 20 and np.abs(read[:, :, :10].astype(int) - 200).max() < 20
    assert np.abs(read[:, -1].astype(int) - read[:, -2].astype(int)).max() < 20  # the repeated row


def test_camera_path_from_args(tmp_path):
    train = SimpleNamespace(c2w=training_cameras(), intrinsics=torch.tensor([[20.0, 20.0, 8.0, 6.0]]).expand(30, 4),
                            width=16, height=12)
    scene = SimpleNamespace(train=train, aabb=torch.tensor([-1.0, -1, -1, 1, 1, 1]))
    args = SimpleNamespace(path="spiral", frames=7, fps=9.0)
    path = video_out.camera_path_from_args(args, scene, tmp_path)
    assert path.c2w.shape == (7, 3, 4) and (path.width, path.height, path.fps) == (16, 12, 9.0)
    args.path = str(tmp_path / "missing.json")
    with pytest.raises(ValueError, match="no such file"):
        video_out.camera_path_from_args(args, scene, tmp_path)
