"""``ngp-warp process``: structure from motion with pycolmap on the demo scene (in its textured
room, rendered from 40 known cameras), frames from videos, and bad input ending in one line."""

import argparse
import json
import math

import numpy as np
import pytest
import torch

pytest.importorskip("pycolmap")
pytest.importorskip("imageio_ffmpeg")

import imageio.v3 as iio  # noqa: E402

from ngp_warp.data import fold_check  # noqa: E402
from ngp_warp.data import process as P  # noqa: E402
from ngp_warp.cli.process import add_process_parser  # noqa: E402
from ngp_warp.data import scene as demo  # noqa: E402
from ngp_warp.data import video as V  # noqa: E402
from ngp_warp.cli import main  # noqa: E402
from ngp_warp.data.data_error import DataError  # noqa: E402

N_VIEWS, SIZE = 40, 256


def _write_views(folder, c2w: np.ndarray, size: int = SIZE) -> None:
    folder.mkdir(parents=True)
    fx = 0.5 * size / math.tan(0.5 * demo.CAMERA_ANGLE_X)
    intrinsics = torch.tensor([[fx, fx, size / 2, size / 2]], dtype=torch.float32).expand(len(c2w), 4)
    rgb = demo.render_room_views(torch.from_numpy(c2w).float(), intrinsics.contiguous(), size, size)
    for i, image in enumerate((rgb * 255 + 0.5).clamp(0, 255).to(torch.uint8).numpy()):
        iio.imwrite(folder / f"{i:03d}.png", image)


@pytest.fixture(scope="module")
def demo_photos(tmp_path_factory):
    """40 photos of the demo scene in its room, and their [40, 3, 4] float64 camera-to-world."""
    c2w, _ = demo.demo_cameras(N_VIEWS, 1, seed=0)
    folder = tmp_path_factory.mktemp("photos") / "images"
    _write_views(folder, c2w)
    return folder, c2w


def test_dense_sift_and_the_global_mapper_pose_the_demo_scene(demo_photos, tmp_path, monkeypatch):
    """The demo scene's 40 views are posed within 1°, and the check against their own matches
    passes; the same matches flag the known poses once half of them is folded onto the other."""
    photos, c2w = demo_photos
    read = []
    database_inliers = fold_check.database_inliers
    monkeypatch.setattr(fold_check, "database_inliers", lambda *a: read.append(database_inliers(*a)) or read[-1])
    report = P.process(photos, tmp_path / "scene", P.ProcessConfig(sift="dense", mapper="global", device="cpu",
                                                                  show_progress=False))
    assert report.registered == N_VIEWS and report.sift_device == "cpu"
    assert report.mapper == "global" and report.contradicted == [] and len(read) == 1
    known = {f"{i:03d}.png": -m[:, 2] for i, m in enumerate(c2w)}  # OpenGL cameras look along -z
    assert len(read[0]) > N_VIEWS and fold_check.contradicted_images(known, read[0]) == []
    turn = np.diag([-1.0, -1.0, 1.0])  # the views of the scene's back (x < 0) posed as its front
    folded = {name: turn @ axis if c2w[int(name[:3]), 0, 3] < 0 else axis for name, axis in known.items()}
    assert len(fold_check.contradicted_images(folded, read[0])) >= 2
    meta = json.loads((tmp_path / "scene" / "transforms.json").read_text())
    index = [int(f["file_path"].split("/")[-1][:3]) for f in meta["frames"]]
    rotation_error, centre_error, _ = P.pose_errors(np.array([f["transform_matrix"] for f in meta["frames"]]),
                                                    c2w[index])
    assert rotation_error.max() < 1.0 and centre_error.max() < 0.01 * demo.CAMERA_RADIUS


def test_process_refuses_an_unknown_mapper_or_sift_in_one_line():
    for setting in ({"mapper": "hierarchical"}, {"sift": "huge"}):
        with pytest.raises(ValueError, match=next(iter(setting))):
            P.ProcessConfig(**setting).check()


def _cli(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(prog="ngp-warp")
    add_process_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["process", *argv])
    args.func(args)


def _leftovers(parent):
    return sorted(p.name for p in parent.iterdir() if ".partial" in p.name)


def test_process_poses_the_demo_scene(demo_photos, tmp_path, capsys):
    photos, c2w = demo_photos
    scene = tmp_path / "out" / "scene"
    assert main(["process", str(photos), "--out", str(scene), "--quiet", "--device", "cpu"]) == 0  # as a user runs it
    line = capsys.readouterr().out.splitlines()[0]
    registered = int(line.split()[1])
    assert line.startswith(f"registered {registered} of {N_VIEWS} images, mean reprojection error")
    assert registered >= 0.9 * N_VIEWS
    meta = json.loads((scene / "transforms.json").read_text())
    assert len(meta["frames"]) == registered
    assert all((scene / f["file_path"]).is_file() for f in meta["frames"])
    assert {p.name for p in scene.iterdir()} == {"images", "sparse", "transforms.json"}
    assert all((scene / "sparse" / "0" / f"{name}.bin").is_file() for name in ("cameras", "images", "points3D"))
    index = [int(f["file_path"].split("/")[-1][:3]) for f in meta["frames"]]
    posed = np.array([f["transform_matrix"] for f in meta["frames"]])
    rotation_error, centre_error, _ = P.pose_errors(posed, c2w[index])
    assert rotation_error.max() < 1.0  # degrees
    assert centre_error.max() < 0.01 * demo.CAMERA_RADIUS
    fx = 0.5 * SIZE / math.tan(0.5 * demo.CAMERA_ANGLE_X)
    assert abs(meta["fl_x"] / fx - 1) < 0.01
    assert _leftovers(scene.parent) == []


def test_pose_errors_undo_a_similarity_and_see_a_moved_camera():
    ref, _ = demo.demo_cameras(12, 1, seed=3)
    rng = np.random.default_rng(1)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    moved = np.concatenate([q @ ref[:, :, :3], 0.3 * (q @ ref[:, :, 3:]) + rng.normal(size=(3, 1))], axis=2)
    rotation_error, centre_error, spread = P.pose_errors(moved, ref)
    assert rotation_error.max() < 1e-5 and centre_error.max() < 1e-9 and spread > 1.0
    turn = np.array([[1, 0, 0], [0, math.cos(0.05), -math.sin(0.05)], [0, math.sin(0.05), math.cos(0.05)]])
    moved[4, :, :3] = moved[4, :, :3] @ turn
    rotation_error, _, _ = P.pose_errors(moved, ref)
    assert rotation_error[4] == pytest.approx(math.degrees(0.05), rel=1e-6)


def _noise_photos(folder, n: int, size: int = 96):
    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(n):
        iio.imwrite(folder / f"{i}.png", rng.integers(0, 256, (size, size, 3), dtype=np.uint8))


@pytest.mark.parametrize("case", ["missing", "no images", "not a video", "two images", "unmatched", "exists",
                                  "mixed sizes", "frames of photos"])
def test_bad_input_is_one_line_and_writes_nothing(tmp_path, case):
    source, scene = tmp_path / "input", tmp_path / "out" / "scene"
    args = []
    if case == "no images":
        source.mkdir()
        (source / "notes.txt").write_text("no photos here")
    elif case == "not a video":
        source = tmp_path / "clip.mp4"
        source.write_text("this is not a video")
    elif case == "two images":
        _noise_photos(source, 2)
    elif case == "unmatched":
        _noise_photos(source, 4)  # features, but no two images share any
    elif case == "exists":
        _noise_photos(source, 4)
        scene.mkdir(parents=True)
        (scene / "mine.txt").write_text("keep me")
    elif case == "mixed sizes":  # one camera for all: an odd size is named
        _noise_photos(source, 4)
        iio.imwrite(source / "2.png", np.zeros((40, 48, 3), dtype=np.uint8) + 7)
    elif case == "frames of photos":
        _noise_photos(source, 4)
        args = ["--frames", "3"]
    with pytest.raises(DataError) as err:
        _cli([str(source), "--out", str(scene), "--quiet", *args])
    assert "\n" not in str(err.value) and str(err.value)
    if case == "exists":
        assert [p.name for p in scene.iterdir()] == ["mine.txt"]
        assert "already exists" in str(err.value)
    elif case == "mixed sizes":
        assert str(err.value).startswith(f"{source / '2.png'}: photo is 48x40 but 3 of 4 are ")
    else:
        assert not (tmp_path / "out").exists()  # not even the parent this call created


def test_interrupt_leaves_nothing(tmp_path, monkeypatch):
    _noise_photos(tmp_path / "input", 4)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(P, "_features_and_matches", interrupted)
    with pytest.raises(KeyboardInterrupt):
        P.process(tmp_path / "input", tmp_path / "scene", P.ProcessConfig(show_progress=False))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["input"]


def test_settings_errors_are_one_line(tmp_path):
    with pytest.raises(SystemExit):  # argparse: --frames and --fps exclude each other
        _cli([str(tmp_path), "--out", str(tmp_path / "s"), "--frames", "3", "--fps", "2"])
    with pytest.raises(SystemExit):  # argparse: a positive count
        _cli([str(tmp_path), "--out", str(tmp_path / "s"), "--frames", "0"])
    with pytest.raises(ValueError, match="frames must be positive"):  # the setting itself, for library callers
        P.ProcessConfig(frames=0).check()


def _blur(image: np.ndarray) -> np.ndarray:
    out = image.astype(np.float32)
    for axis in (0, 1):
        out = sum(np.roll(out, k, axis=axis) for k in range(-3, 4)) / 7.0
    return out.astype(np.uint8)


def test_video_keeps_the_sharpest_frame_of_each_stretch(tmp_path):
    rng = np.random.default_rng(0)
    sharp = [np.kron(rng.integers(0, 256, (20, 20, 3)), np.ones((8, 8, 1))).astype(np.uint8) for _ in range(4)]
    frames, sharp_at = [], [1, 5, 6, 10]  # stretches of 3 frames: [0-2], [3-5], [6-8], [9-11]
    for i in range(12):
        base = sharp[min(range(4), key=lambda k: abs(sharp_at[k] - i))]
        frames.append(base if i in sharp_at else _blur(base))
    video = tmp_path / "clip.mp4"
    iio.imwrite(video, np.stack(frames), fps=12, codec="libx264", quality=10, macro_block_size=16)
    out = tmp_path / "frames"
    out.mkdir()
    written = V.extract_frames(video, out, count=4, show_progress=False)
    assert [p.name for p in written] == [f"frame_0000{i}.jpg" for i in range(1, 5)]
    for path, image in zip(written, sharp):
        kept = iio.imread(path).astype(np.float32)
        assert np.abs(kept - image).mean() < np.abs(kept - _blur(image)).mean()
    assert V.sharpness(sharp[0]) > 4 * V.sharpness(_blur(sharp[0]))
    assert len(V.extract_frames(video, tmp_path, fps=2.0, show_progress=False)) == 2  # 1 s of video


def test_frames_of_a_video_fill_the_scene_images(tmp_path, monkeypatch, caplog):
    video = tmp_path / "clip.mp4"
    rng = np.random.default_rng(2)
    iio.imwrite(video, rng.integers(0, 256, (9, 64, 64, 3), dtype=np.uint8), fps=3, codec="libx264",
                macro_block_size=16)
    seen = {}

    def stop(work, images_dir, sizes, matcher, config, masks):
        seen.update(sizes=sizes, matcher=matcher, masks=masks)
        raise DataError("stop here")

    monkeypatch.setattr(P, "_features_and_matches", stop)
    with pytest.raises(DataError, match="stop here"):
        P.process(video, tmp_path / "scene", P.ProcessConfig(frames=5, show_progress=False))
    assert len(seen["sizes"]) == 5 and seen["matcher"] == "sequential" and seen["masks"] is None
    assert set(seen["sizes"].values()) == {(64, 64)}
    assert not (tmp_path / "scene").exists() and _leftovers(tmp_path) == []
    with pytest.raises(DataError, match="stop here"):  # more frames than the video has: all, and a warning
        P.process(video, tmp_path / "scene", P.ProcessConfig(frames=20, show_progress=False))
    assert len(seen["sizes"]) == 9
    assert caplog.messages == [f"ngp-warp: {video}: the video has 9 frames; all are kept (--frames 20)"]


def test_the_ngp_warp_command_reports_bad_input_in_one_line(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert main(["process", str(tmp_path / "empty"), "--out", str(tmp_path / "scene"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("ngp-warp: error: ") and "Traceback" not in err[0], err
    assert not (tmp_path / "scene").exists() and _leftovers(tmp_path) == []


def test_a_contradicted_model_is_reported_in_plain_words(tmp_path, monkeypatch, capsys):
    def folded_process(source, scene, config):
        return P.ProcessReport(scene=tmp_path / "scene", registered=40, total=40, mean_reprojection_error=0.6,
                               matcher="exhaustive", sift_device="cpu", mapper="incremental",
                               contradicted=["017.png", "025.png"], seconds={"total": 1.0})

    monkeypatch.setattr("ngp_warp.cli.process.process", folded_process)
    assert main(["process", str(tmp_path), "--out", str(tmp_path / "scene"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "incremental mapping" in out and "the global mapper's model contradicted its own matches" in out
    warning = out.splitlines()[-1]
    assert warning.startswith("warning: the poses of 2 image(s) contradict their own matches (017.png, 025.png)")
    assert "folded by a symmetry" in warning
