"""Image files of every mode a capture may hold, read as imageio's Pillow plugin reads them."""

import imageio.v3 as iio
import numpy as np
import pytest
from PIL import Image

from ngp_warp.data.data_error import DataError
from ngp_warp.data.images import read_image


def _pixels(mode: str) -> Image.Image:
    gen = np.random.default_rng(3)
    rgba = gen.integers(0, 256, (6, 5, 4), dtype=np.uint8)
    if mode == "I;16":
        return Image.fromarray(gen.integers(0, 65536, (6, 5), dtype=np.uint16))
    if mode == "P":
        return Image.fromarray(rgba[..., :3]).convert("P", palette=Image.Palette.ADAPTIVE, colors=16)
    return Image.fromarray(rgba).convert(mode)


@pytest.mark.parametrize("mode", ["RGB", "RGBA", "L", "LA", "P", "I;16"])
def test_every_mode_reads_as_imageio_reads_it(tmp_path, mode):
    path = tmp_path / f"image_{mode.replace(';', '')}.png"
    _pixels(mode).save(path)
    want = np.asarray(iio.imread(path, plugin="pillow"))
    if want.dtype == np.uint16:
        want = ((want.astype(np.uint32) * 255 + 32767) // 65535).astype(np.uint8)
    if want.ndim == 2:
        want = want[..., None]
    if want.shape[2] <= 2:
        want = np.concatenate([np.repeat(want[..., :1], 3, axis=2), want[..., 1:]], axis=2)
    got = read_image(path)
    assert got.dtype == np.uint8 and got.shape[:2] == (6, 5) and got.shape[2] in (3, 4)
    np.testing.assert_array_equal(got, want)
    assert len(np.unique(got)) > 4  # not a constant image


@pytest.mark.parametrize("suffix", ["jpg", "tif"])
def test_a_cmyk_file_reads_as_its_rgb(tmp_path, suffix):
    """A CMYK JPEG or TIFF (print workflows) reads as Pillow's RGB of it, not as 4 channels of ink."""
    path = tmp_path / f"image.{suffix}"
    rgb = Image.fromarray(np.random.default_rng(4).integers(0, 256, (6, 5, 3), dtype=np.uint8))
    rgb.convert("CMYK").save(path)
    got = read_image(path)
    assert got.shape == (6, 5, 3)
    with Image.open(path) as image:
        np.testing.assert_array_equal(got, np.asarray(image.convert("RGB")))
    assert np.abs(got.astype(int) - np.asarray(rgb).astype(int)).mean() < 20  # near the colours it was made from


def test_a_truncated_or_foreign_file_is_one_line(tmp_path):
    good = tmp_path / "good.png"
    _pixels("RGB").save(good)
    truncated = tmp_path / "truncated.png"
    truncated.write_bytes(good.read_bytes()[:60])
    foreign = tmp_path / "notes.png"
    foreign.write_text("not an image")
    for path in (truncated, foreign):
        with pytest.raises(DataError, match=f"^{path}: cannot read image") as e:
            read_image(path)
        assert "\n" not in str(e.value)
