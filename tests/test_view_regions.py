"""benchmarks/view_regions.py: photos scored as the evaluation scores them, and each region's
PSNR of a run folder's renders and of another folder of renders."""

import json
import math
import sys

import imageio.v3 as iio
import numpy as np
import torch

from ngp_warp.data.loading import downscale_image
from ngp_warp.outputs.evaluate import composite_on

from benchmark_scripts import load_benchmark

view_regions = load_benchmark("view_regions")


def test_photo_as_scored_is_the_evaluations_ground_truth(tmp_path):
    rgba = np.random.default_rng(0).integers(0, 256, (64, 96, 4), dtype=np.uint8)
    iio.imwrite(tmp_path / "p.png", rgba)
    want = composite_on(torch.from_numpy(downscale_image(rgba, 2)), torch.ones(3)).double().numpy()
    np.testing.assert_allclose(view_regions.photo_as_scored(tmp_path / "p.png", 32, 48), want, atol=1e-6)


def test_regions_split_rows_then_columns():
    error = np.full((6, 4), 1e-2)
    error[4:, 2:] = 1e-4  # bottom right of 3 × 2
    assert view_regions.region_psnr(error, 3, 2) == [20.0] * 5 + [40.0]
    assert view_regions.region_psnr(np.zeros((6, 4)), 1, 1) == [math.inf]


def test_run_and_other_renders_by_region(tmp_path, monkeypatch, capsys):
    rng = np.random.default_rng(1)
    photos, run, other = tmp_path / "images", tmp_path / "run", tmp_path / "other"
    for folder in (photos, run / "renders", other):
        folder.mkdir(parents=True)
    per_image = []
    for name in ("0001", "0012"):
        photo = rng.integers(0, 256, (48, 32, 3), dtype=np.uint8)
        iio.imwrite(photos / f"{name}.jpg", photo, quality=100)
        scored = iio.imread(photos / f"{name}.jpg")  # as decoded
        off = scored.copy()
        off[:16, :16] = 255 - off[:16, :16]  # the other renderer is wrong in the top left only
        iio.imwrite(run / "renders" / f"{name}.png", scored)
        iio.imwrite(other / f"{name}.png", off)
        per_image.append({"image": str(photos / f"{name}.jpg"), "psnr": 1.0})
    (run / "metrics.json").write_text(json.dumps({"per_image": per_image}))
    monkeypatch.setattr(sys, "argv", ["view_regions.py", str(run), "--images", f"other={other}",
                                      "--mosaic", str(tmp_path / "m.png")])
    view_regions.main()
    rows = [line.split("|")[1:-1] for line in capsys.readouterr().out.splitlines() if line.startswith("| 0")]
    assert [(r[0].strip(), r[1].strip()) for r in rows] == [("0001", "run"), ("0001", "other"),
                                                            ("0012", "run"), ("0012", "other")]
    for view, source, *scores in rows:
        scores = [float(s) for s in scores]
        if source.strip() == "run":
            assert all(math.isinf(s) for s in scores)
        else:
            assert scores[0] < 15 and all(math.isinf(s) for s in scores[1:])
    assert iio.imread(tmp_path / "m.png").shape == (2 * 48 // 8, 2 * 32 // 8)
