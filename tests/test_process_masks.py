"""``ngp-warp process --masks``: no COLMAP features where a mask leaves pixels out, the masks
written into the scene and named for training, and bad masks ending in one line."""

import json

import numpy as np
import pytest

pytest.importorskip("pycolmap")
pytest.importorskip("imageio_ffmpeg")

import imageio.v3 as iio  # noqa: E402
import pycolmap  # noqa: E402

from ngp_warp.cli import main  # noqa: E402
from ngp_warp.data import process as P  # noqa: E402
from ngp_warp.data import scene as demo  # noqa: E402
from ngp_warp.data.data_error import DataError  # noqa: E402
from ngp_warp.data.loading import load_scene  # noqa: E402
from ngp_warp.data.process_masks import gather_masks, mask_for  # noqa: E402
from test_process import SIZE, _write_views  # noqa: E402

N_PHOTOS = 10
LEFT = SIZE // 4  # the masks leave out the columns left of this


@pytest.fixture(scope="module")
def photos(tmp_path_factory):
    """10 photos of the demo scene in its room (SIZE × SIZE) from an arc of 90° around it, and a
    folder of their masks, each black on its left quarter (nerfstudio's STEM.png for the even
    photos, COLMAP's NAME.png for the odd ones; palette PNGs whose index 1 is black, so that
    the stored values decide)."""
    azimuth = np.radians(np.linspace(0.0, 90.0, N_PHOTOS))
    c2w = np.stack([demo.look_at(p) for p in demo._on_sphere(azimuth, np.full(N_PHOTOS, 20.0))])
    root = tmp_path_factory.mktemp("masked")
    _write_views(root / "images", c2w)
    (root / "masks").mkdir()
    keep = np.ones((SIZE, SIZE), np.uint8)
    keep[:, :LEFT] = 0
    from PIL import Image

    for i in range(N_PHOTOS):
        name = f"{i:03d}.png" if i % 2 == 0 else f"{i:03d}.png.png"
        mask = Image.fromarray(keep, mode="P")
        mask.putpalette([255, 255, 255, 0, 0, 0])  # index 0 white, 1 black: only the indices count
        mask.save(root / "masks" / name)
    return root


def _keypoints_x(database) -> np.ndarray:
    db = pycolmap.Database.open(str(database))
    try:
        return np.concatenate([db.read_keypoints(im.image_id)[:, 0] for im in db.read_all_images()])
    finally:
        db.close()


@pytest.mark.parametrize("masked", [True, False])
def test_no_features_where_a_mask_leaves_pixels_out(photos, tmp_path, masked):
    sizes = {f"{i:03d}.png": (SIZE, SIZE) for i in range(N_PHOTOS)}
    masks = gather_masks(photos / "masks", sizes, tmp_path) if masked else None
    work = tmp_path / "work"
    work.mkdir()
    config = P.ProcessConfig(sift="standard", device="cpu", show_progress=False)
    database, _ = P._features_and_matches(work, photos / "images", sizes, "exhaustive", config, masks)
    x = _keypoints_x(database)
    assert len(x) > 50 * N_PHOTOS
    if masked:  # COLMAP tests the mask at each keypoint's pixel
        assert x.min() >= LEFT - 1
    else:  # the room has texture there: the masked test above can fail
        assert (x < LEFT - 1).mean() > 0.1


def test_masks_are_written_named_and_trained_on(photos, tmp_path, capsys):
    scene = tmp_path / "scene"
    assert main(["process", str(photos / "images"), "--out", str(scene), "--quiet", "--device", "cpu",
                 "--masks", str(photos / "masks")]) == 0
    assert f"{scene / 'masks'}/" in capsys.readouterr().out
    meta = json.loads((scene / "transforms.json").read_text())
    assert len(meta["frames"]) >= N_PHOTOS - 1
    for frame in meta["frames"]:
        name = frame["file_path"].split("/")[-1]
        assert frame["mask_path"] == f"masks/{name}.png"
        written = iio.imread(scene / frame["mask_path"])
        assert written.dtype == np.uint8 and written.ndim == 2
        assert (written[:, :LEFT] == 0).all() and (written[:, LEFT:] == 255).all()
    model = pycolmap.Reconstruction(str(scene / "sparse" / "0"))  # COLMAP got the masks
    x = np.array([p.xy[0] for image in model.images.values() for p in image.points2D])
    assert len(x) > 100 and x.min() >= LEFT - 1
    split = load_scene(scene).train  # every 8th frame held out
    assert split.masks is not None and split.masks.shape == (len(split.names), SIZE, SIZE)
    assert not split.masks[:, :, :LEFT].any() and split.masks[:, :, LEFT:].all()


def test_mask_names(tmp_path):
    (tmp_path / "a.jpg.png").write_bytes(b"")
    (tmp_path / "b.png").write_bytes(b"")
    assert mask_for("a.jpg", tmp_path) == tmp_path / "a.jpg.png"
    assert mask_for("b.jpg", tmp_path) == tmp_path / "b.png"
    assert mask_for("c.jpg", tmp_path) is None


@pytest.mark.parametrize("case", ["no folder", "one missing", "wrong size", "unreadable", "video", "shared",
                                  "among the photos", "inside the scene"])
def test_bad_masks_are_one_line_and_write_nothing(photos, tmp_path, capsys, case):
    masks = tmp_path / "masks"
    source = photos / "images"
    scene = tmp_path / "scene"
    if case not in ("no folder", "among the photos"):
        masks.mkdir()
        for i in range(N_PHOTOS):
            iio.imwrite(masks / f"{i:03d}.png", np.full((SIZE, SIZE), 255, np.uint8))
    if case == "one missing":
        (masks / "003.png").unlink()
    elif case == "wrong size":
        iio.imwrite(masks / "005.png", np.full((SIZE, SIZE + 2), 255, np.uint8))
    elif case == "unreadable":
        (masks / "002.png").write_bytes(b"not a png")
    elif case == "video":
        source = tmp_path / "clip.mp4"
        iio.imwrite(source, np.zeros((4, 32, 32, 3), np.uint8), fps=4, codec="libx264")
    elif case == "shared":  # 000.png and 000.jpg both find 000.png
        source = tmp_path / "photos"
        source.mkdir()
        for name in ("000.png", "001.png", "002.png"):
            (source / name).write_bytes((photos / "images" / name).read_bytes())
        iio.imwrite(source / "000.jpg", iio.imread(photos / "images" / "003.png"))
    elif case == "among the photos":
        masks = source
    elif case == "inside the scene":  # --overwrite would delete them with the old scene
        scene.mkdir()
        masks = masks.rename(scene / "raw_masks")
    expected = {"no folder": "no such folder", "one missing": f"no mask for 1 of {N_PHOTOS} photos (first: 003.png",
                "wrong size": f"mask is {SIZE + 2}x{SIZE} but its photo 005.png is {SIZE}x{SIZE}",
                "unreadable": "cannot read mask", "video": "masks go with a folder of photos",
                "shared": "photos 000.jpg and 000.png would share the mask 000.png",
                "among the photos": "in a folder of their own", "inside the scene": "inside the scene folder"}[case]
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    assert main(["process", str(source), "--out", str(scene), "--quiet", "--masks", str(masks), "--overwrite"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and expected in err[0], err
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before  # nothing written or lost
    with pytest.raises(DataError):  # the library raises the same
        P.process(source, scene, P.ProcessConfig(masks=masks, show_progress=False))
