"""Training masks (nerfstudio's per-frame ``mask_path``): loaded as the pixels to train on, and
the pixels they leave out change nothing in training."""

import json
import shutil

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from PIL import Image

from ngp_warp.data.data_error import DataError
from ngp_warp.data.loading import load_scene
from ngp_warp.data.scene import write_demo_scene
from ngp_warp.training.config import FieldConfig, TrainConfig
from ngp_warp.training.refined_transforms import refined_transforms
from ngp_warp.training.scene_defaults import plain_backdrop
from ngp_warp.training.train_step import pixels_kept, rays_kept
from ngp_warp.training.trainer import Trainer

W, H = 32, 24  # not square: a mask read as [W, H] fails


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    path = tmp_path_factory.mktemp("masks") / "demo"
    write_demo_scene(path, width=W, height=H, n_train=12, n_test=2, supersample=2)
    return path


def masked_copy(demo, tmp_path, name: str, masks: dict[int, np.ndarray]):
    """A copy of the demo scene whose training frames k in ``masks`` get ``mask_path`` to a PNG
    of that [H, W] bool array."""
    path = tmp_path / name
    shutil.copytree(demo, path)
    meta = json.loads((path / "transforms_train.json").read_text())
    for k, keep in masks.items():
        iio.imwrite(path / f"mask_{k}.png", keep.astype(np.uint8) * 255)
        meta["frames"][k]["mask_path"] = f"mask_{k}.png"
    (path / "transforms_train.json").write_text(json.dumps(meta))
    return path


def left_half_out() -> np.ndarray:
    keep = np.ones((H, W), dtype=bool)
    keep[:, : W // 2] = False
    return keep


def test_masks_load_as_the_pixels_to_train_on(demo, tmp_path):
    odd = np.random.default_rng(0).random((H, W)) > 0.3
    path = masked_copy(demo, tmp_path, "odd", {0: left_half_out(), 3: odd})
    scene = load_scene(path)
    names = [n.split("/")[-1] for n in scene.train.names]
    masks = scene.train.masks
    assert masks.dtype == torch.bool and masks.shape == (12, H, W)
    assert torch.equal(masks[names.index("r_0.png")], torch.from_numpy(left_half_out()))
    assert torch.equal(masks[names.index("r_3.png")], torch.from_numpy(odd))
    others = [k for k, n in enumerate(names) if n not in ("r_0.png", "r_3.png")]
    assert bool(masks[others].all())
    assert load_scene(demo).train.masks is None
    # downscaled: a pixel stays only where its whole 2 x 2 block does
    half = load_scene(path, downscale=2).train.masks[names.index("r_3.png")]
    expect = torch.from_numpy(odd.reshape(H // 2, 2, W // 2, 2).all(axis=(1, 3)))
    assert torch.equal(half, expect) and not bool(expect.all()) and bool(expect.any())


def test_instant_ngp_dynamic_masks_mark_the_pixels_left_out(demo, tmp_path):
    path = masked_copy(demo, tmp_path, "dynamic", {2: left_half_out()})
    out = np.zeros((H, W, 3), np.uint8)
    out[: H // 4, :, 1] = 7  # any nonzero channel leaves a pixel out
    for k in (1, 2):  # frame 2's mask_path takes precedence over its dynamic mask
        iio.imwrite(path / "train" / f"dynamic_mask_r_{k}.png", out)
    scene = load_scene(path)
    names = [n.split("/")[-1] for n in scene.train.names]
    expect = torch.ones(H, W, dtype=torch.bool)
    expect[: H // 4] = False
    assert torch.equal(scene.train.masks[names.index("r_1.png")], expect)
    assert torch.equal(scene.train.masks[names.index("r_2.png")], torch.from_numpy(left_half_out()))


@pytest.mark.parametrize("bad, message", [("missing", "no such file"), (7, "must be a non-empty string"),
                                          ("small", "mask is 16x16 but its image"), ("transposed", "mask is 24x32 but its image")])
def test_a_bad_mask_is_a_one_line_data_error(demo, tmp_path, bad, message):
    path = masked_copy(demo, tmp_path, "bad", {0: left_half_out()})
    meta = json.loads((path / "transforms_train.json").read_text())
    if bad in ("small", "transposed"):
        iio.imwrite(path / "mask_0.png", np.full((16, 16) if bad == "small" else (W, H), 255, np.uint8))
    else:
        meta["frames"][0]["mask_path"] = "nowhere.png" if bad == "missing" else bad
    (path / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match=message) as e:
        load_scene(path)
    assert "\n" not in str(e.value)


def test_rays_kept_combines_both_masks():
    a, b = torch.tensor([True, True, False, False]), torch.tensor([True, False, True, False])
    assert torch.equal(rays_kept(a, b), torch.tensor([True, False, False, False]))
    assert rays_kept(a, None) is a and rays_kept(None, b) is b and rays_kept(None, None) is None
    masks = torch.tensor([[[True, True], [False, False]], [[False, False], [False, True]]])  # [image, row, column]
    pixels = torch.tensor([[0, 1, 0], [0, 0, 1], [1, 1, 1], [1, 0, 1]], dtype=torch.int32)  # image, px, py
    expect = torch.tensor([True, False, True, False]).repeat_interleave(4)
    assert torch.equal(pixels_kept(masks, pixels, 2), expect)
    assert pixels_kept(None, pixels, 2) is None


def trained_table(path) -> torch.Tensor:
    cfg = TrainConfig(steps=12, target_samples=1 << 12, grid_resolution=32, steps_per_diagonal=128,
                      field=FieldConfig(n_levels=4, log2_hashmap_size=12, finest_resolution=64.0, hidden=16))
    trainer = Trainer(load_scene(path), cfg, device="cpu")
    trainer.train(show_progress=False)
    return trainer.field.encoding.params.detach().clone()


def repainted(path, tmp_path, name: str):
    """A copy of ``path`` whose training images have the left half of every image inverted."""
    out = tmp_path / name
    shutil.copytree(path, out)
    for image in (out / "train").iterdir():
        a = iio.imread(image)
        a[:, : W // 2, :3] = 255 - a[:, : W // 2, :3]
        iio.imwrite(image, a)
    return out


def test_pixels_a_mask_leaves_out_change_nothing_in_training(demo, tmp_path):
    masked = masked_copy(demo, tmp_path, "masked", {k: left_half_out() for k in range(12)})
    same = trained_table(masked)
    torch.testing.assert_close(trained_table(repainted(masked, tmp_path, "masked-repainted")), same,
                               rtol=0, atol=1e-6)
    # without the masks, the repainted half does move the training
    unmasked = trained_table(demo)
    assert (trained_table(repainted(demo, tmp_path, "repainted")) - unmasked).abs().max() > 1e-3


def test_palette_masks_read_their_indices_and_an_empty_mask_warns(demo, tmp_path, caplog):
    path = masked_copy(demo, tmp_path, "palette", {0: left_half_out()})
    palette = Image.new("P", (W, H))
    palette.putdata(left_half_out().astype(np.uint8).reshape(-1).tolist())
    palette.putpalette([0, 0, 0, 0, 255, 0] + [0] * 762)  # index 1 (keep) shown green: red channel 0
    palette.save(path / "mask_0.png")
    meta = json.loads((path / "transforms_train.json").read_text())
    iio.imwrite(path / "mask_1.png", np.zeros((H, W), np.uint8))
    meta["frames"][1]["mask_path"] = "mask_1.png"
    (path / "transforms_train.json").write_text(json.dumps(meta))
    scene = load_scene(path)
    names = [n.split("/")[-1] for n in scene.train.names]
    assert torch.equal(scene.train.masks[names.index("r_0.png")], torch.from_numpy(left_half_out()))
    assert "leave out every pixel (first: mask_1.png)" in caplog.text


def test_a_frame_without_its_image_is_skipped_with_its_mask(demo, tmp_path):
    path = masked_copy(demo, tmp_path, "gone", {0: left_half_out()})
    meta = json.loads((path / "transforms_train.json").read_text())
    meta["frames"][1]["file_path"] = "./train/gone"
    meta["frames"][1]["mask_path"] = "gone_mask.png"
    (path / "transforms_train.json").write_text(json.dumps(meta))
    assert len(load_scene(path).train) == 11


def test_refined_transforms_keep_the_masks_where_they_are(demo, tmp_path):
    path = masked_copy(demo, tmp_path, "refined", {3: left_half_out()})
    scene = load_scene(path)
    meta = refined_transforms(path, 1, scene.train.names, scene.train.c2w)
    out = tmp_path / "elsewhere"
    out.mkdir()
    (out / "transforms.json").write_text(json.dumps(meta))
    moved = load_scene(out / "transforms.json", holdout_every=100).train  # holds out r_0 alone
    names = [n.split("/")[-1] for n in moved.names]
    assert torch.equal(moved.masks[names.index("r_3.png")], torch.from_numpy(left_half_out()))


def test_a_plain_backdrop_is_judged_on_the_pixels_masks_keep():
    images = torch.full((4, H, W, 3), 255, dtype=torch.uint8)
    images[:, :, :3] = 20  # a dark strip on the left border, which the masks leave out
    masks = torch.ones(4, H, W, dtype=torch.bool)
    masks[:, :, :3] = False
    assert not plain_backdrop(images) and plain_backdrop(images, masks)
