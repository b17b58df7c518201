"""instant-ngp's frame-choosing and pixel keys (``n_frames``, ``sharpness_discard_threshold``,
``white_transparent`` / ``black_transparent``), the start pose of a moving frame, and the one
warning for the keys ngp-warp reads past (:mod:`ngp_warp.data.ngp_frames`)."""

import json
import logging

import imageio.v3 as iio
import numpy as np
import pytest

from data_fixtures import instant_ngp, random_c2w, write_json
from ngp_warp.data.loading import DataError, load_scene


def _names(scene):
    return sorted(p.split("/")[-1].split(".")[0] for p in (*scene.train.names, *scene.test.names))


def _rewrite(root, meta):
    write_json(root / "transforms.json", meta)
    return load_scene(root / "transforms.json", holdout_every=100)


def _renamed(root, meta, names):
    """``meta`` with its frames' images renamed to ``names`` (unpadded numbers: natural order
    differs from the strings' order), the frames listed in reverse."""
    for frame, name in zip(meta["frames"], names):
        old = next((root / "images").glob(frame["file_path"].split("/")[-1].split(".")[0] + ".*"))
        new = root / "images" / (name + old.suffix)
        old.rename(new)
        frame["file_path"] = f"images/{new.name}"
    meta["frames"] = meta["frames"][::-1]
    return meta


def _stems(scene):
    return sorted((p.split("/")[-1].split(".")[0] for p in (*scene.train.names, *scene.test.names)),
                  key=lambda n: int(n[3:]))


def test_n_frames_keeps_the_first_frames_in_natural_path_order(tmp_path):
    meta, _ = instant_ngp(tmp_path, n=12)
    meta = _renamed(tmp_path, meta, [f"img{i}" for i in range(12)])
    assert _stems(_rewrite(tmp_path, {**meta, "n_frames": 3})) == ["img0", "img1", "img2"]  # not img10, img11
    assert len(_names(_rewrite(tmp_path, {**meta, "n_frames": 50}))) == 12
    for bad in (0, 2.5, "3", True):
        with pytest.raises(DataError, match="n_frames must be a positive integer"):
            _rewrite(tmp_path, {**meta, "n_frames": bad})


def _instant_ngp_sharpness_filter(values, threshold):
    """instant-ngp's loop (nerf_loader.cu), transcribed: the kept indices."""
    kept = []
    for i in range(len(values)):
        start, end = max(0, i - 3), min(i + 3, len(values) - 1)
        mean = sum(values[start:end]) / (end - start) if end > start else float("nan")
        if values[i] > threshold * mean:
            kept.append(i)
    return kept


def test_blurrier_frames_than_their_neighbours_are_left_out(tmp_path):
    meta, _ = instant_ngp(tmp_path, n=12)
    meta = _renamed(tmp_path, meta, [f"img{i}" for i in range(12)])
    # by natural order img0 .. img11; the window's shape (3 before, 2 after, the last frame's
    # without itself) decides frames 6, 10 and 11
    sharpness = [30.0, 31.0, 9.0, 29.0, 33.0, 30.0, 14.0, 30.0, 28.0, 200.0, 55.0, 45.0]
    by_name = {f"img{i}": s for i, s in enumerate(sharpness)}
    for frame in meta["frames"]:
        frame["sharpness"] = by_name[frame["file_path"].split("/")[-1].split(".")[0]]
    assert len(_names(_rewrite(tmp_path, meta))) == 12  # threshold 0: every frame sharper than 0
    kept = {}
    for threshold in (0.5, 0.6):
        kept[threshold] = [f"img{i}" for i in _instant_ngp_sharpness_filter(sharpness, threshold)]
        assert _stems(_rewrite(tmp_path, {**meta, "sharpness_discard_threshold": threshold})) == kept[threshold]
    assert kept[0.5] != kept[0.6] and len(kept[0.6]) < 12
    meta["frames"][0]["sharpness"] = 0.0  # instant-ngp's threshold 0 still drops a frame of sharpness 0
    assert len(_names(_rewrite(tmp_path, meta))) == 11
    with pytest.raises(DataError, match="no frame is sharper"):
        _rewrite(tmp_path, {**meta, "sharpness_discard_threshold": 100.0})


def test_sharpness_counts_only_when_the_first_frame_in_order_has_it(tmp_path):
    meta, _ = instant_ngp(tmp_path, n=4)
    for frame in meta["frames"]:
        del frame["sharpness"]
    meta["frames"][3]["sharpness"] = 0.0  # the last by name: instant-ngp never looks at it
    assert len(_names(_rewrite(tmp_path, {**meta, "sharpness_discard_threshold": 0.5}))) == 4


@pytest.mark.parametrize("key, value", [("white_transparent", 255), ("black_transparent", 0)])
def test_white_or_black_pixels_become_transparent(tmp_path, key, value):
    meta, _ = instant_ngp(tmp_path, n=3)
    rng = np.random.default_rng(1)
    image = rng.integers(1, 255, size=(6, 8, 3), dtype=np.uint8)
    image[2:4, 3:6] = value
    image[0, 0] = (value, value, 128)  # two channels alone do not make a pixel transparent
    for i in range(3):
        iio.imwrite(tmp_path / f"images/{i:04d}.png", image)
        meta["frames"][i]["file_path"] = f"images/{i:04d}.png"
    plain = _rewrite(tmp_path, meta).train.images
    assert plain.shape[-1] == 3
    scene = _rewrite(tmp_path, {**meta, key: True})
    alpha = scene.train.images[0, ..., 3].numpy()
    expected = np.full((6, 8), 255, np.uint8)
    expected[2:4, 3:6] = 0
    assert np.array_equal(alpha, expected)
    assert np.array_equal(scene.train.images[0, ..., :3].numpy(), image)
    with pytest.raises(DataError, match=f"{key} must be true or false"):
        _rewrite(tmp_path, {**meta, key: "yes"})


def test_messages_name_the_files_own_frame_number(tmp_path):
    meta, _ = instant_ngp(tmp_path, n=5)
    meta["frames"] = meta["frames"][::-1]  # file frame 0 is the last by name
    del meta["frames"][0]["transform_matrix"]
    with pytest.raises(DataError, match="frame 0: missing transform_matrix"):
        _rewrite(tmp_path, {**meta, "n_frames": 5})


def test_a_moving_frame_takes_its_start_pose(tmp_path):
    meta, _ = instant_ngp(tmp_path, n=3)
    start = random_c2w(np.random.default_rng(5))
    frame = meta["frames"][1]
    frame["transform_matrix_start"] = start.tolist()
    frame["transform_matrix_end"] = frame.pop("transform_matrix")
    scene = _rewrite(tmp_path, meta)
    assert np.allclose(scene.train.c2w[0].double().numpy(), start[:3], atol=1e-5)


def test_keys_read_past_are_named_in_one_warning(tmp_path, caplog):
    meta, _ = instant_ngp(tmp_path, n=3)
    meta["frames"][1]["transform_matrix_start"] = meta["frames"][1]["transform_matrix"]  # a start pose alone: applied
    with caplog.at_level(logging.WARNING):
        _rewrite(tmp_path, meta)
    assert "does not apply" not in caplog.text
    meta = {**meta, "rolling_shutter": [0.0, 0.01, 0.0, 0.0], "sharpen": 0.5, "envmap": "sky.exr",
            "integer_depth_scale": 0.001}
    meta["frames"][0]["depth_path"] = "depth/0000.png"
    alpha = tmp_path / "images/0000.alpha.png"  # frame 0's file_path leaves out its image's extension
    iio.imwrite(alpha, np.zeros((6, 8, 3), np.uint8))
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        _rewrite(tmp_path, meta)
    lines = [r.getMessage() for r in caplog.records if "does not apply" in r.getMessage()]
    assert len(lines) == 1
    for key in ("rolling_shutter", "sharpen", "depth_path", "envmap", ".alpha."):
        assert key in lines[0]
    caplog.clear()
    quiet = {**meta, "rolling_shutter": [0, 0, 0, 0], "sharpen": 0, "integer_depth_scale": 0}
    del quiet["envmap"]
    alpha.unlink()
    with caplog.at_level(logging.WARNING):
        _rewrite(tmp_path, quiet)  # zeros and a depth scale of 0 change nothing
    assert "does not apply" not in caplog.text
