"""Dataset parsing (NeRF-synthetic, instant-ngp), lenses, missing frames, downscaling and the
bad-input messages. COLMAP folders: test_colmap.py; the camera models: test_cameras.py."""

import json
import logging
import math
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from data_fixtures import fov_to_focal, instant_ngp, nerf_synthetic, random_c2w, write_json

from ngp_warp.data.loading import (DataError, Split, downscale_image, image_rays, load_scene, normalisation_record,
                           write_normalisation)

FOX = Path(__file__).resolve().parents[2] / "shared" / "data" / "fox"


# ---- NeRF-synthetic ---------------------------------------------------------------------------

def test_nerf_synthetic_loads_images_cameras_and_box(tmp_path):
    written = nerf_synthetic(tmp_path, n_train=3, n_test=2, size=(8, 6), angle=0.69)
    scene = load_scene(tmp_path)
    assert scene.source == "nerf-synthetic" and not scene.test_is_heldout
    assert scene.occupancy_levels == 1
    assert scene.aabb.tolist() == [-1.5, -1.5, -1.5, 1.5, 1.5, 1.5]
    assert torch.equal(scene.occupancy_aabb, scene.aabb)
    for split, name in ((scene.train, "train"), (scene.test, "test")):
        meta, images = written[name]
        assert split.images.dtype == torch.uint8 and split.images.shape == (len(images), 6, 8, 4)
        assert (split.width, split.height) == (8, 6)
        np.testing.assert_array_equal(split.images.numpy(), np.stack(images))
        c2w = np.array([f["transform_matrix"] for f in meta["frames"]])[:, :3]
        np.testing.assert_allclose(split.c2w.numpy(), c2w, rtol=1e-6, atol=1e-6)
        f = fov_to_focal(8, 0.69)
        np.testing.assert_allclose(split.intrinsics.numpy(), np.tile([f, f, 4.0, 3.0], (len(images), 1)), rtol=1e-6)
        assert not split.has_distortion and split.distortion.abs().sum() == 0
        assert [n.rsplit("/", 1)[-1] for n in split.names] == [f"r_{i}.png" for i in range(len(images))]


def test_nerf_synthetic_without_test_split_holds_out_frames(tmp_path):
    nerf_synthetic(tmp_path, n_train=7, with_test=False)
    scene = load_scene(tmp_path, holdout_every=3)
    assert scene.test_is_heldout and scene.source == "nerf-synthetic"
    stem = lambda names: [n.rsplit("/", 1)[-1] for n in names]  # noqa: E731
    assert stem(scene.test.names) == ["r_0.png", "r_3.png", "r_6.png"]
    assert stem(scene.train.names) == ["r_1.png", "r_2.png", "r_4.png", "r_5.png"]


# ---- instant-ngp ---------------------------------------------------------------------------------

def test_instant_ngp_keys_paths_formats_and_holdout(tmp_path):
    meta, images = instant_ngp(tmp_path, n=7, size=(8, 6))
    # frame 2 overrides the focal length (a frame giving only fl_x sets fy = fx too, as in
    # instant-ngp), the principal point and k1
    meta["frames"][2].update({"fl_x": 9.0, "cx": 3.5, "k1": -0.2})
    write_json(tmp_path / "transforms.json", meta)
    scene = load_scene(tmp_path / "transforms.json", holdout_every=3)
    assert scene.source == "instant-ngp" and scene.test_is_heldout
    assert len(scene.train) == 4 and len(scene.test) == 3
    order = [0, 3, 6, 1, 2, 4, 5]  # test frames first, then train
    got = torch.cat([scene.test.images, scene.train.images]).numpy()
    assert got.shape == (7, 6, 8, 4)  # RGB and JPG frames gain an opaque alpha channel
    for k, i in enumerate(order):
        rgb = images[i][..., :3]
        alpha = images[i][..., 3] if images[i].shape[-1] == 4 else np.full(rgb.shape[:2], 255)
        np.testing.assert_array_equal(got[k, ..., :3], rgb)
        np.testing.assert_array_equal(got[k, ..., 3], alpha)
    intr = torch.cat([scene.test.intrinsics, scene.train.intrinsics]).numpy()
    dist = torch.cat([scene.test.distortion, scene.train.distortion]).numpy()
    for k, i in enumerate(order):
        want = [9.0, 9.0, 3.5, 2.75] if i == 2 else [7.5, 7.0, 4.25, 2.75]
        np.testing.assert_allclose(intr[k], want, rtol=1e-6)
        np.testing.assert_allclose(dist[k], [-0.2 if i == 2 else 0.05, -0.01, 0, 0, 0.002, -0.001], rtol=1e-6)
    assert scene.train.has_distortion and not scene.train.fisheye
    torch.testing.assert_close(scene.world_from_scene, torch.eye(4, dtype=torch.float64))
    # default scale 0.33, offset 0.5: the box [0.5 -+ 2]^3 of the unit cube, mapped to the world
    assert scene.occupancy_levels == 3
    np.testing.assert_allclose(scene.aabb.numpy(), [-2 / 0.33] * 3 + [2 / 0.33] * 3, rtol=1e-6)
    assert scene.near == pytest.approx(0.1 / 0.33, rel=1e-5)


def test_nerfstudio_split_lists_choose_the_test_frames(tmp_path, caplog):
    meta, _ = instant_ngp(tmp_path, n=7, size=(8, 6))
    names = [f"images/{i:04d}." + ("jpg" if i % 3 == 2 else "png") for i in range(7)]
    write_json(tmp_path / "transforms.json", {**meta, "val_filenames": [names[5], "./" + names[6]]})
    scene = load_scene(tmp_path)
    assert not scene.test_is_heldout
    assert [Path(n).stem for n in scene.test.names] == ["0005", "0006"] and len(scene.train) == 5
    listed = {**meta, "train_filenames": names[:3], "val_filenames": names[5:], "test_filenames": [names[4]]}
    write_json(tmp_path / "transforms.json", listed)  # test_filenames first; frame 3 in neither list
    scene = load_scene(tmp_path)
    assert [Path(n).stem for n in scene.test.names] == ["0004"]
    assert [Path(n).stem for n in scene.train.names] == ["0000", "0001", "0002"]
    write_json(tmp_path / "transforms.json", {**meta, "test_filenames": ["images/nope.png"]})
    with pytest.raises(DataError, match="none of the 1 files test_filenames names is among the frames"):
        load_scene(tmp_path)
    write_json(tmp_path / "transforms.json", {**meta, "test_filenames": names[1:2], "train_filenames": names[:3]})
    with caplog.at_level(logging.WARNING):
        load_scene(tmp_path)
    assert "1 of the 1 frames test_filenames names are in train_filenames too" in caplog.text


def test_instant_ngp_scale_offset_and_aabb_key(tmp_path):
    instant_ngp(tmp_path, n=3, aabb_scale=16, scale=0.5, offset=[0.5, 0.25, 1.0])
    scene = load_scene(tmp_path)
    assert scene.occupancy_levels == 5
    lo = [(0.5 - 8 - o) / 0.5 for o in (0.5, 0.25, 1.0)]
    hi = [(0.5 + 8 - o) / 0.5 for o in (0.5, 0.25, 1.0)]
    np.testing.assert_allclose(scene.aabb.numpy(), lo + hi, rtol=1e-6)
    cascade = [(0 - o) / 0.5 for o in (0.5, 0.25, 1.0)] + [(1 - o) / 0.5 for o in (0.5, 0.25, 1.0)]
    np.testing.assert_allclose(scene.occupancy_aabb.numpy(), cascade, rtol=1e-6)
    # the coarsest of the 5 cascades (finest box x 2^4 about its centre) is the field's box
    centre, half = scene.occupancy_aabb.view(2, 3).mean(0), scene.occupancy_aabb.view(2, 3).diff(dim=0) / 2
    torch.testing.assert_close(torch.cat([centre - 16 * half[0], centre + 16 * half[0]]), scene.aabb)
    instant_ngp(tmp_path, n=3, aabb_scale=1, aabb=[[-1.0, 0.0, 2.0], [3.0, 2.0, 4.0]])
    np.testing.assert_allclose(load_scene(tmp_path).aabb.numpy(), [-1, -1, 1, 3, 3, 5], atol=1e-5)


def test_focal_from_angles_fov_and_json_resolution(tmp_path):
    meta, _ = instant_ngp(tmp_path, n=2, size=(8, 6))
    for k in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
        del meta[k]
    meta["camera_angle_x"] = 0.9
    meta["frames"][1]["camera_angle_y"] = 0.5  # a frame with only y: fx = fy
    write_json(tmp_path / "transforms.json", meta)
    scene = load_scene(tmp_path)
    fx = fov_to_focal(8, 0.9)
    fy = fov_to_focal(6, 0.5)
    np.testing.assert_allclose(scene.test.intrinsics[0].numpy(), [fx, fx, 4.0, 3.0], rtol=1e-6)
    np.testing.assert_allclose(scene.train.intrinsics[0].numpy(), [fy, fy, 4.0, 3.0], rtol=1e-6)
    # x_fov (degrees) beats fl_x; pixel intrinsics given for w x h are rescaled to the image
    meta["x_fov"] = 60.0
    del meta["frames"][1]["camera_angle_y"]
    meta["frames"][1].update({"fl_x": 20.0, "w": 16, "h": 12, "cx": 6.0, "cy": 5.0})
    write_json(tmp_path / "transforms.json", meta)
    scene = load_scene(tmp_path)
    f60 = fov_to_focal(8, math.radians(60.0))
    np.testing.assert_allclose(scene.test.intrinsics[0].numpy(), [f60, f60, 4.0, 3.0], rtol=1e-6)
    np.testing.assert_allclose(scene.train.intrinsics[0].numpy(), [10.0, 10.0, 3.0, 2.5], rtol=1e-6)


# ---- downscaling ---------------------------------------------------------------------------

def test_downscale_area_average_rgb_with_crop():
    rng = np.random.default_rng(1)
    a = rng.integers(0, 256, size=(9, 7, 3), dtype=np.uint8)
    got = downscale_image(a, 2)
    want = np.floor(a[:8, :6].astype(float).reshape(4, 2, 3, 2, 3).mean(axis=(1, 3)) + 0.5)
    np.testing.assert_array_equal(got, want.astype(np.uint8))


def test_downscale_rgba_commutes_with_compositing():
    rng = np.random.default_rng(2)
    a = rng.integers(0, 256, size=(12, 12, 4), dtype=np.uint8)
    a[:3, :3, 3] = 0  # one block fully transparent
    for bg in (0.0, 255.0):
        comp = a[..., :3] * (a[..., 3:] / 255.0) + bg * (1 - a[..., 3:] / 255.0)
        want = comp.reshape(4, 3, 4, 3, 3).mean(axis=(1, 3))
        d = downscale_image(a, 3).astype(float)
        got = d[..., :3] * (d[..., 3:] / 255.0) + bg * (1 - d[..., 3:] / 255.0)
        assert np.abs(got - want).max() <= 1.01  # uint8 rounding of rgb and alpha


def test_load_with_downscale_divides_intrinsics(tmp_path):
    written = nerf_synthetic(tmp_path, n_train=2, n_test=1, size=(9, 8), angle=0.7)
    scene = load_scene(tmp_path, downscale=2)
    assert scene.train.images.shape == (2, 4, 4, 4) and (scene.train.width, scene.train.height) == (4, 4)
    np.testing.assert_array_equal(scene.train.images[1].numpy(), downscale_image(written["train"][1][1], 2))
    f = fov_to_focal(9, 0.7) / 2
    np.testing.assert_allclose(scene.train.intrinsics[0].numpy(), [f, f, 2.25, 2.0], rtol=1e-6)


# ---- bad inputs -------------------------------------------------------------------------------

def _frames(tmp_path):
    return json.loads((tmp_path / "transforms_train.json").read_text())


def _edit(tmp_path, change):
    meta = _frames(tmp_path)
    change(meta)
    write_json(tmp_path / "transforms_train.json", meta)


def _set(key, value, frame=1):
    def change(meta):
        meta["frames"][frame][key] = value
    return change


BAD_LAST_ROW = [[2, 0, 0, 0], [0, 2, 0, 0], [0, 0, 2, 0], [0, 1, 0, 1]]
BAD = {
    "no frames key": (lambda p: _edit(p, lambda m: m.pop("frames")), "transforms_train.json: no 'frames' list"),
    "zero frames": (lambda p: _edit(p, lambda m: m.update(frames=[])), "transforms_train.json: no frames"),
    "frame not object": (lambda p: _edit(p, lambda m: m["frames"].__setitem__(1, 3)), "frame 1: expected an object"),
    "no file_path": (lambda p: _edit(p, lambda m: m["frames"][1].pop("file_path")), "frame 1: missing file_path"),
    "no matrix": (lambda p: _edit(p, lambda m: m["frames"][1].pop("transform_matrix")),
                  "frame 1: missing transform_matrix"),
    "matrix shape": (lambda p: _edit(p, _set("transform_matrix", [[1, 0], [0, 1]])), "frame 1: transform_matrix must be"),
    "matrix text": (lambda p: _edit(p, _set("transform_matrix", "eye")), "frame 1: transform_matrix must be"),
    "matrix nan": (lambda p: _edit(p, _set("transform_matrix", [[float("nan")] * 4] * 4)), "frame 1: transform_matrix has non-finite"),
    "singular": (lambda p: _edit(p, _set("transform_matrix", [[1, 0, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])),
                 "frame 1: transform_matrix is singular"),
    "no image left": (lambda p: [f.unlink() for f in (p / "train").iterdir()],
                      "transforms_train.json: none of the 3 frames has its image (first missing:"),
    "mixed sizes": (lambda p: iio.imwrite(p / "train" / "r_2.png", np.zeros((4, 4, 4), np.uint8)),
                    "r_2.png: image is 4x4 but the first image (r_0.png) is 8x6"),
    "unreadable image": (lambda p: (p / "test" / "r_0.png").write_bytes(b"not a png at all"), "r_0.png: cannot read image"),
    "truncated image": (lambda p: (p / "train" / "r_1.png").write_bytes((p / "train" / "r_1.png").read_bytes()[:60]),
                        "r_1.png: cannot read image"),
    "no focal": (lambda p: _edit(p, lambda m: m.pop("camera_angle_x")), "frame 0: no focal length"),
    "focal text": (lambda p: _edit(p, lambda m: m.update(camera_angle_x="wide")), "camera_angle_x must be a number"),
    "focal negative": (lambda p: _edit(p, _set("fl_x", -3.0)), "frame 1: fl_x must be positive"),
    "angle too wide": (lambda p: _edit(p, lambda m: m.update(camera_angle_x=4.0)), "camera_angle_x must be below a half turn"),
    "latlong": (lambda p: _edit(p, lambda m: m.update(latlong=True)), "lens model with 'latlong' is not supported"),
    "ftheta at p0 = 0": (lambda p: _edit(p, lambda m: m.update(ftheta_p0=0.0, ftheta_p1=300.0)),
                         "lens model with 'ftheta_p0' is not supported"),
    "camera model": (lambda p: _edit(p, lambda m: m.update(camera_model="EQUIRECTANGULAR")),
                     "camera_model 'EQUIRECTANGULAR' is not supported (OPENCV, PINHOLE"),
    "k4 perspective": (lambda p: _edit(p, _set("k4", 0.01)), "frame 1: k4 is only used by OPENCV_FISHEYE"),
    "p1 fisheye": (lambda p: _edit(p, lambda m: m.update(camera_model="OPENCV_FISHEYE", p1=0.01)),
                   "OPENCV_FISHEYE has no tangential terms"),
    "mixed lenses": (lambda p: _edit(p, _set("is_fisheye", True, frame=2)),
                     "frame 2: mixes fisheye and perspective cameras"),
    "bad world_from_scene": (lambda p: _edit(p, lambda m: m.update(world_from_scene=BAD_LAST_ROW)),
                             "world_from_scene's bottom row must be [0, 0, 0, 1]"),
    "bad json": (lambda p: (p / "transforms_train.json").write_text('{"frames": [\n  {"file_path": }\n]}'),
                 "transforms_train.json: not valid JSON (Expecting value at line 2, column 17)"),
    "json list": (lambda p: (p / "transforms_train.json").write_text("[1, 2]"), "expected a JSON object"),
    "bad offset": (lambda p: _edit(p, lambda m: m.update(offset=[1, 2])), "offset must be a number or a list of 3"),
    "bad aabb_scale": (lambda p: _edit(p, lambda m: m.update(aabb_scale=0)), "aabb_scale must be positive"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_raises_one_line_naming_the_file(tmp_path, case):
    nerf_synthetic(tmp_path, n_train=3, n_test=1, size=(8, 6))
    spoil, message = BAD[case]
    spoil(tmp_path)
    with pytest.raises(DataError) as e:
        load_scene(tmp_path)
    text = str(e.value)
    assert message in text and "\n" not in text
    assert str(tmp_path) in text


@pytest.mark.parametrize("case", ["missing folder", "empty folder", "single frame", "downscale too big", "downscale zero"])
def test_bad_paths_and_arguments(tmp_path, case):
    kwargs, target = {}, tmp_path
    if case == "missing folder":
        target, message = tmp_path / "nope", "nope: no such file or folder"
    elif case == "empty folder":
        message = "no transforms_train.json, transforms.json or COLMAP sparse/0/ in this folder"
    elif case == "single frame":
        instant_ngp(tmp_path, n=1)
        message = "transforms.json: only 1 frame"
    elif case == "downscale too big":
        nerf_synthetic(tmp_path, size=(8, 6))
        kwargs, message = {"downscale": 7}, "image is 8x6, smaller than downscale 7"
    else:
        nerf_synthetic(tmp_path)
        kwargs, message = {"downscale": 0}, "downscale must be a positive integer"
    with pytest.raises(DataError) as e:
        load_scene(target, **kwargs)
    assert message in str(e.value) and "\n" not in str(e.value)
    assert isinstance(e.value, ValueError)


# ---- splits and rays ------------------------------------------------------------------------------

def test_split_validates_and_moves():
    n = 2
    good = dict(images=torch.zeros(n, 4, 5, 3, dtype=torch.uint8), c2w=torch.zeros(n, 3, 4),
                intrinsics=torch.ones(n, 4), distortion=torch.zeros(n, 6), names=["a", "b"], width=5, height=4)
    s = Split(**good).to("cpu")
    assert len(s) == 2 and not s.has_distortion and s.lens_model == 0
    fish = Split(**good, fisheye=True).to("cpu")
    assert fish.fisheye and fish.has_distortion and fish.lens_model == 2  # equidistant even with zeros
    for key, bad in (("images", torch.zeros(n, 5, 4, 3, dtype=torch.uint8)), ("c2w", torch.zeros(n, 4, 4)),
                     ("intrinsics", torch.ones(n, 4, dtype=torch.float64)), ("names", ["a"]),
                     ("distortion", torch.zeros(n, 4)),
                     ("images", torch.zeros(n, 4, 5, 2, dtype=torch.uint8))):
        with pytest.raises(ValueError):
            Split(**{**good, key: bad})


def test_image_rays_are_row_major_and_match_the_cameras(tmp_path):
    nerf_synthetic(tmp_path, n_train=2, n_test=1, size=(8, 6))
    split = load_scene(tmp_path).train
    o, d = image_rays(split, 1)
    assert o.shape == d.shape == (48, 3)
    torch.testing.assert_close(o, split.c2w[1, :, 3].expand(48, 3))
    fx, fy, cx, cy = split.intrinsics[1].tolist()
    k = 2 * 8 + 5  # row 2, column 5
    cam = torch.tensor([(5.5 - cx) / fx, -(2.5 - cy) / fy, -1.0])
    want = split.c2w[1, :, :3] @ cam
    torch.testing.assert_close(d[k], want / want.norm())
    with pytest.raises(ValueError):
        image_rays(split, 2)


def test_random_cameras_fixture_is_valid():
    c2w = random_c2w(np.random.default_rng(0))
    np.testing.assert_allclose(c2w[:3, :3] @ c2w[:3, :3].T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(c2w[:3, 2], c2w[:3, 3] / 4.0, atol=1e-12)  # +z points away from the origin


def test_aabb_scale_beyond_the_cascades_is_refused(tmp_path):
    instant_ngp(tmp_path, n=3, aabb_scale=2**16)
    with pytest.raises(DataError, match="aabb_scale 65536 is larger than 32768"):
        load_scene(tmp_path)


# ---- lenses, missing frames, the normalisation record ------------------------------------------

def test_lens_keys_camera_model_and_is_fisheye(tmp_path):
    meta, _ = instant_ngp(tmp_path, n=4, k3=0.003)
    scene = load_scene(tmp_path)
    assert not scene.train.fisheye and scene.train.lens_model == 1
    np.testing.assert_allclose(scene.train.distortion[0].numpy(), [0.05, -0.01, 0.003, 0, 0.002, -0.001], rtol=1e-6)
    for lens in ({"camera_model": "OPENCV_FISHEYE"}, {"is_fisheye": True}):
        instant_ngp(tmp_path, n=4, p1=0.0, p2=0.0, k3=0.003, k4=-0.002, **lens)
        scene = load_scene(tmp_path)
        assert scene.train.fisheye and scene.test.fisheye and scene.train.lens_model == 2
        np.testing.assert_allclose(scene.test.distortion[0].numpy(), [0.05, -0.01, 0.003, -0.002, 0, 0], rtol=1e-6)
    instant_ngp(tmp_path, n=4, camera_model="PINHOLE", k1=0.0, k2=0.0, p1=0.0, p2=0.0)
    assert load_scene(tmp_path).train.lens_model == 0


def test_frames_whose_image_is_missing_are_skipped_with_one_warning(tmp_path, caplog):
    meta, _ = instant_ngp(tmp_path, n=9)
    for i in (2, 5, 6):
        next((tmp_path / "images").glob(f"{i:04d}.*")).unlink()
    with caplog.at_level(logging.WARNING, logger="ngp_warp.data.loading"):
        scene = load_scene(tmp_path, holdout_every=3)
    assert len(caplog.records) == 1
    assert "transforms.json: skipped 3 of 9 frames whose image is missing (first: " in caplog.records[0].message
    names = [Path(n).stem for n in scene.test.names + scene.train.names]
    assert sorted(names) == ["0000", "0001", "0003", "0004", "0007", "0008"]
    assert [Path(n).stem for n in scene.test.names] == ["0000", "0004"]  # every 3rd of the frames left


def test_normalisation_record_is_written_whole(tmp_path):
    meta, _ = instant_ngp(tmp_path, n=3)
    m = [[0.0, -2.0, 0.0, 1.0], [2.0, 0.0, 0.0, -3.0], [0.0, 0.0, 2.0, 0.5], [0.0, 0.0, 0.0, 1.0]]
    write_json(tmp_path / "transforms.json", {**meta, "world_from_scene": m})
    scene = load_scene(tmp_path)
    np.testing.assert_array_equal(scene.world_from_scene.numpy(), m)
    path = write_normalisation(tmp_path, scene)
    record = json.loads(path.read_text())
    assert record == normalisation_record(scene) and record["world_from_scene"] == m
    assert record["scale"] == pytest.approx(2.0) and record["source"] == "instant-ngp"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["images", "normalisation.json", "transforms.json"]


@pytest.mark.slow
@pytest.mark.skipif(not (FOX / "transforms.json").is_file(),
                    reason="instant-ngp's fox sample is not in ../shared/data/fox")
def test_instant_ngp_fox_loads_as_shipped(caplog):
    with caplog.at_level(logging.WARNING, logger="ngp_warp.data.loading"):
        scene = load_scene(FOX, downscale=8)
    assert len(caplog.records) == 1 and "skipped 17 of 67 frames whose image is missing" in caplog.records[0].message
    assert len(scene.train) + len(scene.test) == 50 and scene.source == "instant-ngp"
    assert (scene.train.width, scene.train.height) == (135, 240)
    assert scene.train.lens_model == 1 and scene.occupancy_levels == 3
    for split in (scene.train, scene.test):
        o, d = image_rays(split, len(split) - 1)
        assert torch.isfinite(o).all() and torch.isfinite(d).all()
        torch.testing.assert_close(d.norm(dim=-1), torch.ones(len(d)))
