"""Malformed scene folders and settings through the CLI, in-process on the CPU: each ends in exit
code 2 with exactly one error line and no traceback, and a trained folder ("golden") that the
commands point at stays byte-for-byte the same."""

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from ngp_warp.cli import main
from ngp_warp.data.scene import write_demo_scene

CPU = ["--device", "cpu", "--quiet", "--no-video"]


def folder_digest(root: Path) -> dict:
    """{relative path: SHA-256} of every file under ``root`` (folders by their listing)."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir"
            for p in sorted(root.rglob("*"))}


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    path = tmp_path_factory.mktemp("fuzz") / "scene"
    write_demo_scene(path, width=16, height=16, n_train=8, n_test=2, supersample=1)
    return path


@pytest.fixture(scope="module")
def golden(scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("fuzz") / "golden"
    assert main(["train", str(scene), "--out", str(out), "--steps", "10", "--target-samples", "2048", *CPU]) == 0
    return out


def mutate(scene: Path, root: Path, name: str, edit) -> Path:
    """A copy of ``scene`` named ``name`` under ``root`` with ``edit(meta, folder)`` applied to its
    transforms_train.json (``meta`` the parsed file; return False to leave the file as edit left it)."""
    folder = root / name
    shutil.copytree(scene, folder)
    meta = json.loads((folder / "transforms_train.json").read_text())
    if edit(meta, folder) is not False:
        (folder / "transforms_train.json").write_text(json.dumps(meta))
    return folder


def _frame(key, value):
    def edit(meta, folder):
        meta["frames"][0][key] = value
    return edit


def _top(key, value):
    def edit(meta, folder):
        meta[key] = value
    return edit


def _matrix(scale=1.0, shear=0.0, fill=None):
    def edit(meta, folder):
        m = np.array(meta["frames"][1]["transform_matrix"], dtype=float)
        m[:3, :3] *= scale
        m[0, 1] += shear
        meta["frames"][1]["transform_matrix"] = m.tolist() if fill is None else [[fill] * 4] * 4
    return edit


def _file(name, content):
    def edit(meta, folder):
        target = folder / name
        if target.is_dir():
            shutil.rmtree(target)
        elif target.exists():
            target.unlink()
        if content is None:
            target.mkdir()
        else:
            target.write_bytes(content)
        return False
    return edit


def _image(index, content):
    def edit(meta, folder):
        (folder / (meta["frames"][index]["file_path"] + ".png")).write_bytes(content)
    return edit


def _text(make):
    def edit(meta, folder):
        (folder / "transforms_train.json").write_text(make(meta))
        return False
    return edit


def _every_frame_at_the_first_pose(meta, folder):
    for frame in meta["frames"]:
        frame["transform_matrix"] = meta["frames"][0]["transform_matrix"]


def _image_replaced(index, by):
    def edit(meta, folder):
        image = folder / (meta["frames"][index]["file_path"] + ".png")
        image.unlink()
        image.mkdir() if by == "folder" else image.symlink_to(image)
        return False
    return edit


def _all_images_gone(meta, folder):
    shutil.rmtree(folder / "train")


def _no_frames(meta, folder):
    meta["frames"] = []


SCENE_CASES = {
    "not_json": _file("transforms_train.json", b"{not json"),
    "json_list": _file("transforms_train.json", b"[1, 2]"),
    "json_empty": _file("transforms_train.json", b""),
    "json_binary": _file("transforms_train.json", b"\xff\xfe\x00garbage"),
    "test_split_is_folder": _file("transforms_test.json", None),
    "test_split_not_json": _file("transforms_test.json", b"nope"),
    "no_frames": _no_frames,
    "frames_not_list": _top("frames", {"a": 1}),
    "frame_not_object": _top("frames", [1, 2, 3]),
    "all_images_missing": _all_images_gone,
    "no_transform": _frame("transform_matrix", None),
    "matrix_wrong_shape": _frame("transform_matrix", [[1, 0], [0, 1]]),
    "matrix_strings": _frame("transform_matrix", [["a"] * 4] * 4),
    "matrix_nan": _matrix(fill=float("nan")),
    "matrix_singular": _matrix(fill=0.0),
    "rotation_scaled_1000": _matrix(scale=1000.0),
    "rotation_scaled_0.5": _matrix(scale=0.5),
    "rotation_sheared": _matrix(shear=0.5),
    "file_path_number": _frame("file_path", 7),
    "file_path_empty": _frame("file_path", ""),
    "angle_zero": _top("camera_angle_x", 0),
    "angle_negative": _top("camera_angle_x", -1.0),
    "angle_half_turn": _top("camera_angle_x", 3.2),
    "angle_string": _top("camera_angle_x", "wide"),
    "angle_bool": _top("camera_angle_x", True),
    "no_focal": lambda meta, folder: meta.pop("camera_angle_x"),
    "fl_x_zero": _top("fl_x", 0.0),
    "w_other_aspect": lambda meta, folder: meta.update(w=32, h=8),
    "w_zero": lambda meta, folder: meta.update(w=0, h=16),
    "k1_huge": _top("k1", 1e6),
    "k1_fold": _top("k1", -50.0),
    "k2_string": _top("k2", "x"),
    "k4_on_opencv": _top("k4", 0.1),
    "fisheye_with_p1": lambda meta, folder: meta.update(camera_model="OPENCV_FISHEYE", p1=0.1),
    "camera_model_unknown": _top("camera_model", "EQUIRECT"),
    "latlong_lens": _top("latlong", True),
    "aabb_scale_zero": _top("aabb_scale", 0),
    "aabb_scale_too_big": _top("aabb_scale", 65536),
    "aabb_scale_nan": _top("aabb_scale", float("nan")),
    "aabb_bad": _top("aabb", [[0, 0], [1, 1]]),
    "offset_bad": _top("offset", [1, 2]),
    "scale_negative": _top("scale", -1.0),
    "contraction_bad": _top("contraction", "sphere"),
    "world_from_scene_bad": _top("world_from_scene", [[1, 0, 0, 0]] * 4),
    "json_nested_deeply": _text(lambda meta: '{"frames": ' + "[" * 100000 + "]" * 100000 + "}"),
    "json_integer_beyond_float": _text(lambda meta: json.dumps(meta).replace('"camera_angle_x": ',
                                                                              '"camera_angle_x": 1' + "0" * 400 + ', "x": ')),
    "matrix_bottom_row": _frame("transform_matrix", [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0.5, 0, 0, 2]]),
    "every_frame_one_pose": _every_frame_at_the_first_pose,
    "camera_at_1e30": _frame("transform_matrix", [[1, 0, 0, 1e30], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]),
    "image_is_a_folder": _image_replaced(0, "folder"),
    "image_is_a_link_loop": _image_replaced(0, "loop"),
    "image_not_png": _image(0, b"this is not an image"),
    "image_empty": _image(1, b""),
}


@pytest.mark.parametrize("case", sorted(SCENE_CASES))
def test_malformed_scene_is_one_line(case, scene, golden, tmp_path, capsys):
    before = folder_digest(golden)
    folder = mutate(scene, tmp_path, case, SCENE_CASES[case])
    capsys.readouterr()
    code = main(["train", str(folder), "--out", str(tmp_path / "out"), "--steps", "2", "--target-samples", "1024", *CPU])
    assert_one_error_line(code, capsys)
    assert not (tmp_path / "out").exists()
    assert folder_digest(golden) == before


def assert_one_error_line(code, capsys):
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if "error" in line.lower()]
    assert code == 2, err
    assert len(lines) == 1, err
    assert "Traceback" not in err


def settings_cases(scene: Path, golden: Path, tmp: Path) -> dict:
    """{name: argv} of bad settings and bad uses of a trained folder."""
    train = ["train", str(scene), "--out"]
    new = train + [str(tmp / "new")]
    cases = {f"set_{s}": new + ["--set", s] for s in (
        "lr=inf", "lr=nan", "lr=-1", "lr=abc", "seconds=inf", "bogus=1", "field.bogus=1", "noequals",
        "grid_resolution=100000", "grid_resolution=0", "grid_resolution=1", "grid_resolution=2",
        "field.log2_hashmap_size=40", "field.hidden=100000", "field.geo_features=100000",
        "field.finest_resolution=1e30", "loss=l1",
        "weight_average=1", "supersample=9", "steps_per_diagonal=-3", "cone_angle=nan", "seed=-5")}
    cases.update({
        "seed_huge": new + ["--seed", "99999999999999999999999"],
        "steps_zero": new + ["--steps", "0"],
        "seconds_inf": new + ["--seconds", "inf"],
        "frames_negative": new + ["--frames", "-2"],
        "frames_a_billion": new + ["--frames", str(10**9)],
        "steps_beyond_int64": new + ["--steps", str(2**64)],
        "out_name_too_long": train + [str(tmp / ("x" * 300))],
        "out_holds_the_scene": train + [str(scene.parent)],
        "render_fps_near_zero": ["render", str(golden), "--video", "v.gif", "--fps", "1e-300"],
        "render_frames_a_billion": ["render", str(golden), "--video", "v.gif", "--frames", str(10**9)],
        "fit_many_out_is_the_scenes": ["fit-many", str(scene.parent / "scen*"), "--out", str(scene.parent),
                                       "--steps", "1"],
        "out_empty": train + [""],
        "device_tpu": new + ["--device", "tpu"],
        "into_golden": train + [str(golden)],
        "overwrite_bad_setting": train + [str(golden), "--overwrite", "--set", "bogus=1"],
        "overwrite_too_large": train + [str(golden), "--overwrite", "--set", "grid_resolution=100000"],
        "overwrite_diverges": train + [str(golden), "--overwrite", "--steps", "30", "--set", "lr=1e30"],
        "resume_and_overwrite": train + [str(golden), "--resume", "--overwrite"],
        "resume_other_downscale": train + [str(golden), "--resume", "--downscale", "2"],
        "resume_with_set": train + [str(golden), "--resume", "--set", "lr=1"],
        "resume_missing_scene": ["train", str(tmp / "nowhere"), "--out", str(golden), "--resume"],
        "eval_other_scene": ["eval", str(golden), "--scene", str(tmp / "other")],
        "eval_empty": ["eval", ""],
        "eval_missing": ["eval", str(tmp / "missing")],
        "render_bad_video": ["render", str(golden), "--video", "x.avi"],
        "demo_tpu": ["demo", "--out", str(tmp / "demo"), "--device", "tpu"],
        "demo_bogus": ["demo", "--out", str(tmp / "demo"), "--set", "bogus=1"],
    })
    return cases


SETTINGS = sorted(settings_cases(Path("s"), Path("g"), Path("t")))


@pytest.mark.parametrize("case", SETTINGS)
def test_bad_settings_and_uses_are_one_line(case, scene, golden, tmp_path, capsys):
    before = folder_digest(golden)
    write_demo_scene(tmp_path / "other", width=16, height=16, n_train=5, n_test=1, supersample=1, seed=3)
    argv = settings_cases(scene, golden, tmp_path)[case]
    capsys.readouterr()
    extra = ([] if "--device" in argv else ["--device", "cpu"]) + (["--quiet"] if argv[0] != "render" else [])
    try:
        code = main(argv + extra)
    except SystemExit as e:  # argparse's own errors: usage line + one error line
        code = e.code
    assert_one_error_line(code, capsys)
    assert folder_digest(golden) == before
    assert not (tmp_path / "new").exists() and not (tmp_path / "demo").exists()


CHECKPOINT_EDITS = {
    "train_config_a_list": lambda state: state.__setitem__("train_config", [1]),
    "scene_record_a_string": lambda state: state.__setitem__("scene", "lego"),
    "scene_path_a_number": lambda state: state["scene"].__setitem__("path", 5),
    "downscale_a_string": lambda state: state["scene"].__setitem__("downscale", "x"),
    "downscale_zero": lambda state: state["scene"].__setitem__("downscale", 0),
    "field_settings_a_string": lambda state: state["train_config"].__setitem__("field", "x"),
    "step_a_string": lambda state: state.__setitem__("step", "x"),
    "step_negative": lambda state: state.__setitem__("step", -3),
    "train_seconds_nan": lambda state: state.__setitem__("train_seconds", float("nan")),
}


@pytest.mark.parametrize("case", sorted(CHECKPOINT_EDITS))
def test_hand_edited_checkpoints_are_one_line(case, golden, tmp_path, capsys):
    import torch

    run = tmp_path / "run"
    shutil.copytree(golden, run)
    state = torch.load(run / "checkpoint.pt", weights_only=False)
    CHECKPOINT_EDITS[case](state)
    torch.save(state, run / "checkpoint.pt")
    before = folder_digest(run)
    capsys.readouterr()
    assert_one_error_line(main(["eval", str(run), "--device", "cpu", "--quiet"]), capsys)
    assert folder_digest(run) == before
