"""Where in the image a run's held-out error is: each test view's PSNR per region (a grid of
rows × columns), for one or more runs and other renderers' images of the same views, and a
mosaic of their error maps.

    python benchmarks/view_regions.py RUN [RUN ...] [--images LABEL=DIR ...] [--rows 3 --cols 2]
        [--mosaic regions.png]

A RUN is a finished run folder: its ``renders/`` (with appearance codes: each view's code fitted
on its left half) against the photos its ``metrics.json`` names, composited on white and
area-averaged to the render's size. ``--images LABEL=DIR`` adds a folder of PNG renders named as
the views (``DIR/0001.png`` for ``images/0001.jpg``), e.g. instant-ngp's. Prints one table: per
view and source the PSNR of each region (rows top to bottom, columns left to right), and the
mean over views of each region. Sources that disagree by decibels in one region and not in the
others point at what is there (floaters near a camera, reflections, an edge of the capture).
``--mosaic`` writes the error maps (mean squared error over 8 × 8 pixel blocks, on a log scale
from 1e-4, black, to 1e-1, white), one row per view, one column per source.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from ngp_warp.data.loading import downscale_image
from ngp_warp.outputs.evaluate import composite_on

BLOCK = 8  # pixels per side of an error map's block


def photo_as_scored(path: Path, height: int, width: int) -> np.ndarray:
    """The photo at ``path`` as the evaluation scores it: [H, W, 3] float64 in [0, 1], RGBA
    composited on white, area-averaged by the integer factor down to ``height`` × ``width``."""
    image = np.asarray(iio.imread(path))
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    factor = image.shape[0] // height
    if factor < 1 or image.shape[0] // factor != height or image.shape[1] // factor != width:
        raise SystemExit(f"{path}: {image.shape[1]}x{image.shape[0]} is not an integer multiple of the "
                         f"render's {width}x{height}")
    return composite_on(torch.from_numpy(downscale_image(image, factor)), torch.ones(3)).double().numpy()


def region_psnr(error: np.ndarray, rows: int, cols: int) -> list[float]:
    """PSNR of each of ``rows`` × ``cols`` regions (row-major) of a squared-error map [H, W]."""
    h, w = error.shape
    cells = [error[r * h // rows:(r + 1) * h // rows, c * w // cols:(c + 1) * w // cols]
             for r in range(rows) for c in range(cols)]
    return [math.inf if cell.mean() == 0 else -10.0 * math.log10(cell.mean()) for cell in cells]


def error_map(error: np.ndarray) -> np.ndarray:
    """A squared-error map [H, W] as a uint8 picture of its 8 × 8-block means, log scale."""
    h, w = error.shape[0] // BLOCK, error.shape[1] // BLOCK
    blocks = error[:h * BLOCK, :w * BLOCK].reshape(h, BLOCK, w, BLOCK).mean((1, 3))
    scaled = (np.log10(np.maximum(blocks, 1e-12)) + 4.0) / 3.0
    return (np.clip(scaled, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def sources(runs: list[Path], images: list[str]) -> tuple[list[str], list[Path], list[Path]]:
    """(labels, render folders, the views' photo paths) of the runs and ``LABEL=DIR`` folders."""
    metrics = json.loads((runs[0] / "metrics.json").read_text())
    photos = [Path(m["image"]) for m in metrics["per_image"]]
    labels, folders = [run.name for run in runs], [run / "renders" for run in runs]
    for item in images:
        label, _, folder = item.partition("=")
        if not folder:
            raise SystemExit(f"--images {item!r}: give LABEL=DIR")
        labels.append(label)
        folders.append(Path(folder))
    return labels, folders, photos


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="finished run folders (renders/, metrics.json)")
    parser.add_argument("--images", action="append", default=[], metavar="LABEL=DIR",
                        help="PNG renders of the same views from elsewhere, named as the views")
    parser.add_argument("--rows", type=int, default=3)
    parser.add_argument("--cols", type=int, default=2)
    parser.add_argument("--mosaic", type=Path, help="write the error maps here (PNG)")
    args = parser.parse_args()
    labels, folders, photos = sources(args.runs, args.images)
    names = [f"r{r}c{c}" for r in range(args.rows) for c in range(args.cols)]
    print(f"PSNR by region ({args.rows} rows × {args.cols} columns, r0c0 top left)")
    print("| view | source | " + " | ".join(names) + " |\n|---|---|" + "---:|" * len(names))
    table, mosaic_rows = {label: [] for label in labels}, []
    for photo in photos:
        maps = []
        for label, folder in zip(labels, folders):
            render = iio.imread(folder / f"{photo.stem}.png")[..., :3].astype(np.float32) / np.float32(255.0)
            error = ((render - photo_as_scored(photo, *render.shape[:2])) ** 2).mean(-1)
            scores = region_psnr(error, args.rows, args.cols)
            table[label].append(scores)
            maps.append(error_map(error))
            print(f"| {photo.stem} | {label} | " + " | ".join(f"{s:.2f}" for s in scores) + " |")
        mosaic_rows.append(np.concatenate(maps, axis=1))
    for label in labels:  # the mean of each region's PSNR over the views
        print(f"| mean | {label} | " + " | ".join(f"{s:.2f}" for s in np.mean(table[label], axis=0)) + " |")
    if args.mosaic:
        iio.imwrite(args.mosaic, np.concatenate(mosaic_rows, axis=0))
        print(f"wrote {args.mosaic} (rows: views; columns: {', '.join(labels)})")


if __name__ == "__main__":
    sys.exit(main())
