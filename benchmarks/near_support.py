"""How much of a training image the field explains with density close to its camera.

    python benchmarks/near_support.py RUN_DIR --images 0014.jpg,0018.jpg [--start 2.5] [--bands 12]

Renders each named training image with its own appearance code (none where the field has no
codes) twice: its rays started at the trained near distance, and started at ``--start`` (world
units, default twice the near). Prints PSNR against the photo for each band of rows, for both
renders. Where a band loses much with the later start, the field explains that band's pixels
with density between the two distances. An opaque floater that held-out views see near a
training camera (``floaters.py``'s surface rows) lives there.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from fit_study import trainer_or_usage_error
from ngp_warp.outputs.evaluate import composite_on
from ngp_warp.outputs.metrics import psnr


def band_psnrs(trainer, index: int, start: float, bands: int) -> list[tuple[int, int, float, float]]:
    """Rows (first, last + 1) of each of ``bands`` bands of training image ``index``, and the
    band's PSNR against the photo rendered from the trained near and from ``start``."""
    split = trainer.train_split
    camera = split.camera(index)
    background = trainer.view_background
    photo = composite_on(split.images[index].to(trainer.device), torch.ones(3, device=trainer.device))  # as scored
    code = None if trainer.field.appearance is None else trainer.field.appearance.weight[index].detach()
    near = trainer.model.march.near
    renders = []
    for first in (near, start):
        trainer.model.start_rays_at(first)
        try:
            with torch.no_grad():
                renders.append(trainer.render_image(**camera, background=background, appearance_code=code)["rgb"])
        finally:
            trainer.model.start_rays_at(near)
    edges = [round(i * split.height / bands) for i in range(bands + 1)]
    return [(lo, hi, psnr(renders[0][lo:hi], photo[lo:hi]), psnr(renders[1][lo:hi], photo[lo:hi]))
            for lo, hi in zip(edges[:-1], edges[1:])]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run")
    ap.add_argument("--images", required=True, help="comma-separated training image names (file names)")
    ap.add_argument("--start", type=float, default=None, help="the later start, world units (default: 2 × the near)")
    ap.add_argument("--bands", type=int, default=12)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = ap.parse_args()
    trainer = trainer_or_usage_error(ap, args.run, args.device)
    if not 1 <= args.bands <= trainer.train_split.height:
        ap.error(f"--bands must be 1 to the images' {trainer.train_split.height} rows, got {args.bands}")
    names = [Path(n).name for n in trainer.train_split.names]
    start = 2.0 * trainer.model.march.near if args.start is None else args.start
    if not trainer.model.march.near < start < trainer.model.march.far:
        ap.error(f"--start must lie between the near {trainer.model.march.near:g} and the far "
                 f"{trainer.model.march.far:g}, got {start:g}")
    for name in args.images.split(","):
        if name not in names:
            ap.error(f"no training image {name!r}; the training images are {', '.join(names)}")
        print(f"\n{name}: PSNR by rows, rays from the near {trainer.model.march.near:g} and from {start:g}")
        print("| rows | from the near | from the later start | difference |")
        print("| --- | ---: | ---: | ---: |")
        for lo, hi, trained, later in band_psnrs(trainer, names.index(name), start, args.bands):
            print(f"| {lo}–{hi - 1} | {trained:.2f} | {later:.2f} | {later - trained:+.2f} |")


if __name__ == "__main__":
    main()
