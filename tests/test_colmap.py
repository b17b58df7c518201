"""COLMAP folders: models written by the test (.bin and .txt, every supported camera model)
give the rays COLMAP's own projection equations give; normalisation; images_N; bad input."""

import json
import logging
import struct

import numpy as np
import pytest
import torch
from data_fixtures import COLMAP_TEST_PARAMS, colmap_scene, write_colmap, write_json

from ngp_warp.data.colmap import camera_to_world, colmap_to_transforms, read_colmap_model
from ngp_warp.data.loading import DataError, image_rays, load_scene


def _rotation(qvec):
    w, x, y, z = np.asarray(qvec) / np.linalg.norm(qvec)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def colmap_project(model: str, params, qvec, tvec, points: np.ndarray) -> np.ndarray:
    """[P, 2] pixel coordinates of world points, COLMAP's camera equations written out by hand."""
    cam = points @ _rotation(qvec).T + tvec
    x, y = cam[:, 0] / cam[:, 2], cam[:, 1] / cam[:, 2]
    r2 = x * x + y * y
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        f, cx, cy, *k = params
        fx = fy = f
        radial = 1 + sum(kk * r2 ** (i + 1) for i, kk in enumerate(k))
        xd, yd = x * radial, y * radial
    elif model in ("PINHOLE", "OPENCV"):
        fx, fy, cx, cy, *k = params
        k1, k2, p1, p2 = k if k else (0, 0, 0, 0)
        radial = 1 + k1 * r2 + k2 * r2 * r2
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + 2 * p2 * x * y + p1 * (r2 + 2 * y * y)
    else:  # OPENCV_FISHEYE
        fx, fy, cx, cy, k1, k2, k3, k4 = params
        r = np.sqrt(r2)
        theta = np.arctan(r)
        theta_d = theta * (1 + k1 * theta**2 + k2 * theta**4 + k3 * theta**6 + k4 * theta**8)
        xd, yd = x * theta_d / r, y * theta_d / r
    return np.stack([fx * xd + cx, fy * yd + cy], axis=-1)


@pytest.mark.parametrize("binary", [True, False], ids=["bin", "txt"])
@pytest.mark.parametrize("model", sorted(COLMAP_TEST_PARAMS))
def test_rays_land_where_colmap_projects_them(tmp_path, model, binary):
    written = colmap_scene(tmp_path, model, binary=binary)
    scene = load_scene(tmp_path, holdout_every=4)
    assert scene.source == "colmap" and scene.test_is_heldout
    assert len(scene.train) == 3 and len(scene.test) == 2
    assert scene.train.fisheye == (model == "OPENCV_FISHEYE")
    m = scene.world_from_scene.numpy()
    for split in (scene.train, scene.test):
        for k, name in enumerate(split.names):
            _, q, t, _, _ = next(im for im in written["images"] if name.endswith(im[4]))
            o, d = (a.double().numpy() for a in image_rays(split, k))
            o_world, d_world = o @ m[:3, :3].T + m[:3, 3], d @ m[:3, :3].T
            centre = -_rotation(q).T @ t
            np.testing.assert_allclose(o_world, np.broadcast_to(centre, o_world.shape), atol=1e-5)
            pixels = colmap_project(model, written["cameras"][0][4], q, t, o_world + 1.5 * d_world)
            ys, xs = np.mgrid[0:10, 0:12]
            want = np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], axis=-1)
            np.testing.assert_allclose(pixels, want, atol=2e-4)


def test_the_scene_is_normalised_and_maps_back(tmp_path):
    written = colmap_scene(tmp_path, "PINHOLE", n=12)
    scene = load_scene(tmp_path)
    c2w = torch.cat([scene.train.c2w, scene.test.c2w]).double()
    centres = c2w[:, :, 3]
    assert centres.norm(dim=-1).mean().item() == pytest.approx(4.0, rel=1e-5)  # the cameras' focus at the origin
    up = c2w[:, :, 1].mean(0)
    assert (up / up.norm())[2].item() > 0.999  # the cameras' mean up is +z
    lo, hi = scene.aabb[:3].double(), scene.aabb[3:].double()
    assert ((centres > lo) & (centres < hi)).all()
    m = scene.world_from_scene
    scale = torch.linalg.det(m[:3, :3]).item() ** (1 / 3)
    torch.testing.assert_close(m[:3, :3] @ m[:3, :3].T, torch.eye(3, dtype=torch.float64) * scale**2)
    # every camera maps back onto its COLMAP pose (the scene keeps the frames' order by name)
    back = torch.einsum("ij,njk->nik", m[:3, :3], c2w[:, :, :3]) / scale
    want = torch.from_numpy(written["c2w"])
    order = [int(n[-6:-4]) for n in scene.train.names + scene.test.names]  # frame_NN.png
    assert sorted(order) == list(range(12))
    torch.testing.assert_close(back, want[order, :3, :3], atol=1e-6, rtol=0)
    # the sparse points lie inside the field's box
    pts = (torch.from_numpy(written["xyz"]) - m[:3, 3]) @ torch.linalg.inv(m[:3, :3]).T
    assert ((pts > lo) & (pts < hi)).all()


def test_downscale_reads_images_n_when_there(tmp_path):
    colmap_scene(tmp_path, "OPENCV", size=(12, 10))
    full = load_scene(tmp_path, downscale=2)  # no images_2/: images/ area-averaged
    assert (full.train.width, full.train.height) == (6, 5)
    (tmp_path / "images_2").mkdir()
    rng = np.random.default_rng(1)
    import imageio.v3 as iio

    for p in sorted((tmp_path / "images").iterdir()):
        iio.imwrite(tmp_path / "images_2" / p.name, rng.integers(0, 256, (5, 6, 3), dtype=np.uint8))
    small = load_scene(tmp_path, downscale=2)
    assert all("/images_2/" in n for n in small.train.names)
    np.testing.assert_array_equal(small.train.images[0].numpy(),
                                  np.concatenate([iio.imread(small.train.names[0]),
                                                  np.full((5, 6, 1), 255, np.uint8)], axis=-1)[..., :3])
    torch.testing.assert_close(small.train.intrinsics, full.train.intrinsics)
    p = COLMAP_TEST_PARAMS["OPENCV"]
    torch.testing.assert_close(small.train.intrinsics[0], torch.tensor(p[:4]) / 2)


def test_missing_images_are_skipped_and_the_transforms_dict_round_trips(tmp_path, caplog):
    colmap_scene(tmp_path, "OPENCV_FISHEYE", n=6)
    (tmp_path / "images" / "frame_03.png").unlink()
    with caplog.at_level(logging.WARNING, logger="ngp_warp.data.loading"):
        direct = load_scene(tmp_path)
    assert len(caplog.records) == 1 and "skipped 1 of 6 frames whose image is missing" in caplog.messages[0]
    meta = colmap_to_transforms(read_colmap_model(tmp_path / "sparse" / "0"))
    assert meta["camera_model"] == "OPENCV_FISHEYE" and meta["is_fisheye"] and "fl_x" in meta
    write_json(tmp_path / "transforms.json", json.loads(json.dumps(meta)))  # what `process` would write
    via_json = load_scene(tmp_path / "transforms.json")
    for a, b in ((direct.train, via_json.train), (direct.test, via_json.test)):
        assert a.names == b.names and a.fisheye and b.fisheye
        for x, y in zip(image_rays(a, 0), image_rays(b, 0)):
            torch.testing.assert_close(x, y)
    torch.testing.assert_close(direct.world_from_scene, via_json.world_from_scene)


def test_images_txt_without_its_points_lines_reads_every_image(tmp_path):
    """Hand-written models often give each image one line, leaving out the 2-D points line."""
    colmap_scene(tmp_path, "PINHOLE", n=6, binary=False)
    text = tmp_path / "sparse" / "0" / "images.txt"
    standard = read_colmap_model(text.parent).images
    lines = [line for line in text.read_text().splitlines() if line.endswith(".png")]  # the image lines
    assert len(lines) == 6
    text.write_text("# one line per image\n" + "\n".join(lines) + "\n")
    one_line = read_colmap_model(text.parent).images
    assert [im.name for im in one_line] == [im.name for im in standard] and len(one_line) == 6
    for a, b in zip(one_line, standard):
        np.testing.assert_allclose(a.qvec, b.qvec)
        np.testing.assert_allclose(a.tvec, b.tvec)
    text.write_text("\n".join(f"{line}\n1.5 2.5 -1 3.5 4.5 7" for line in lines) + "\n")  # with points
    assert [im.name for im in read_colmap_model(text.parent).images] == [im.name for im in standard]


def test_cameras_that_differ_get_per_frame_intrinsics(tmp_path):
    written = colmap_scene(tmp_path, "PINHOLE", n=4)
    cameras = written["cameras"] + [(2, "SIMPLE_RADIAL", 12, 10, COLMAP_TEST_PARAMS["SIMPLE_RADIAL"])]
    images = [(iid, q, t, 1 + k % 2, name) for k, (iid, q, t, _, name) in enumerate(written["images"])]
    write_colmap(tmp_path / "sparse" / "0", cameras, images, written["xyz"], np.zeros((40, 3), np.uint8), True)
    meta = colmap_to_transforms(read_colmap_model(tmp_path / "sparse" / "0"))
    assert "fl_x" not in meta and [f["fl_x"] for f in meta["frames"]] == [11.0, 11.0, 11.0, 11.0]
    assert [f.get("k1", 0.0) for f in meta["frames"]] == [0.0, -0.08, 0.0, -0.08]
    scene = load_scene(tmp_path, holdout_every=2)
    assert scene.train.has_distortion and not scene.test.has_distortion  # frames 1, 3 have k1
    c2w = camera_to_world(read_colmap_model(tmp_path / "sparse" / "0").images[0])
    np.testing.assert_allclose(c2w, written["c2w"][0], atol=1e-12)


# ---- bad input -------------------------------------------------------------------------------

def _truncate(path, keep=-5):
    path.write_bytes(path.read_bytes()[:keep])


def _cameras_bin(path, model_id, params):
    path.write_bytes(struct.pack("<QiiQQ", 1, 1, model_id, 12, 10) + struct.pack(f"<{len(params)}d", *params))


BAD = {
    "truncated cameras": (lambda s: _truncate(s / "cameras.bin"), "cameras.bin: truncated file (ends inside camera 1)"),
    "truncated images": (lambda s: _truncate(s / "images.bin", 30), "images.bin: truncated file (ends inside image 0)"),
    "truncated points": (lambda s: _truncate(s / "points3D.bin"),
                         "points3D.bin: truncated file (ends inside the track"),
    "trailing bytes": (lambda s: (s / "cameras.bin").write_bytes((s / "cameras.bin").read_bytes() + b"xyz"),
                       "cameras.bin: 3 unexpected bytes after the last record"),
    "unknown model id": (lambda s: _cameras_bin(s / "cameras.bin", 99, [1.0, 2.0, 3.0]),
                         "cameras.bin: camera 1 has unknown camera model id 99"),
    "unsupported model": (lambda s: _cameras_bin(s / "cameras.bin", 7, [11.0, 10.0, 6.0, 5.0, 0.9]),
                          "sparse/0: camera 1: camera model FOV is not supported (SIMPLE_PINHOLE, PINHOLE,"),
    "no points file": (lambda s: (s / "points3D.bin").unlink(), "points3D.bin: missing (a COLMAP model needs"),
    "dangling camera": (lambda s: (s / "cameras.bin").write_bytes(struct.pack("<QiiQQ4d", 1, 7, 1, 12, 10, 1, 1, 6, 5)),
                        "uses camera 1, which cameras.bin does not have"),
    "images folder empty": (lambda s: [p.unlink() for p in (s.parents[1] / "images").iterdir()],
                            "sparse/0: none of the 5 frames has its image (first missing:"),
    "no images folder": (lambda s: (s.parents[1] / "images").rename(s.parents[1] / "pictures"),
                         ": no images/ folder beside the COLMAP model in sparse/0/"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_binary_models_raise_one_line_and_write_nothing(tmp_path, case):
    colmap_scene(tmp_path, "OPENCV")
    spoil, message = BAD[case]
    spoil(tmp_path / "sparse" / "0")
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    with pytest.raises(DataError) as e:
        load_scene(tmp_path)
    assert message in str(e.value) and "\n" not in str(e.value) and str(tmp_path) in str(e.value)
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before


@pytest.mark.parametrize("case", ["unknown model", "parameter count", "malformed number", "short line"])
def test_bad_text_models_raise_one_line(tmp_path, case):
    colmap_scene(tmp_path, "PINHOLE", binary=False)
    sparse = tmp_path / "sparse" / "0"
    if case == "unknown model":
        (sparse / "cameras.txt").write_text("1 FISHEYE_9000 12 10 1 2 3\n")
        message = "cameras.txt: line 1: unknown camera model 'FISHEYE_9000'"
    elif case == "parameter count":
        (sparse / "cameras.txt").write_text("# one camera\n1 PINHOLE 12 10 11 10 6\n")
        message = "cameras.txt: line 2: camera model PINHOLE takes 4 parameters, got 3"
    elif case == "malformed number":
        (sparse / "points3D.txt").write_text("1 0.5 zero 2 10 20 30 0.1\n")
        message = "points3D.txt: line 1 is malformed"
    else:
        (sparse / "images.txt").write_text("1 1 0 0 0 0 0\n\n")
        message = "images.txt: line 1 has 7 fields, expected at least 10"
    with pytest.raises(DataError) as e:
        load_scene(tmp_path)
    assert message in str(e.value) and "\n" not in str(e.value)


def test_folder_without_any_scene(tmp_path):
    (tmp_path / "images").mkdir()
    with pytest.raises(DataError, match="no transforms_train.json, transforms.json or COLMAP sparse/0/"):
        load_scene(tmp_path)
