"""Where the test error is: squared error split by the ground truth's alpha (background,
silhouette edges, object interior), for test and training views, at a few checkpoints.

    python benchmarks/error_regions.py ../shared/data/lego_half [--checkpoints 15,60,120] [--set KEY=VALUE]

Floaters show as background error and opacity there; blurred geometry or texture as interior
error. Needs a scene whose images have an alpha channel. The schedule runs over the last
checkpoint (``--set seconds=S`` to change it).
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from bench_train import scene_or_usage_error, warm_up
from ngp_warp.training.config import TrainConfig, apply_overrides
from ngp_warp.data.loading import Split
from ngp_warp.outputs.evaluate import composite_on
from ngp_warp.training.trainer import Trainer

REGIONS = {"background": (0.0, 0.02), "edges": (0.02, 0.98), "interior": (0.98, 1.01)}


def error_regions(trainer: Trainer, split: Split, every: int) -> dict:
    """Mean PSNR, and per region: share of pixels, share of squared error, PSNR; plus the mean
    rendered opacity over background pixels."""
    sums = {k: [0.0, 0] for k in REGIONS}
    psnrs, bg_opacity = [], []
    white = torch.ones(3, device=trainer.device)
    for i in range(0, len(split), every):
        out = trainer.render_image(split.c2w[i], split.intrinsics[i], split.width, split.height)
        rgba = split.images[i].to(trainer.device)
        alpha = rgba[..., 3].float() / 255.0
        se = (out["rgb"] - composite_on(rgba, white)).square().mean(-1)
        psnrs.append(float(-10 * torch.log10(se.mean())))
        for name, (lo, hi) in REGIONS.items():
            m = (alpha >= lo) & (alpha < hi)
            sums[name][0] += float(se[m].sum())
            sums[name][1] += int(m.sum())
        bg_opacity.append(float(out["opacity"][alpha < 0.02].mean()))
    total_se, total_px = sum(v[0] for v in sums.values()), sum(v[1] for v in sums.values())
    return {"psnr": float(np.mean(psnrs)), "background_opacity": float(np.mean(bg_opacity)),
            **{k: {"pixels": n / total_px, "error": e / total_se, "psnr": float(-10 * np.log10(e / max(n, 1)))}
               for k, (e, n) in sums.items()}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--checkpoints", default="15,60,120")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args()

    marks = [float(s) for s in args.checkpoints.split(",")]
    scene = scene_or_usage_error(ap, args.scene)
    if scene.test.images.shape[-1] != 4:
        ap.error("the scene's images have no alpha channel")
    try:
        cfg = apply_overrides(TrainConfig(seconds=marks[-1]), args.set)
    except ValueError as e:
        ap.error(str(e))
    warm_up(scene, cfg, args.device)
    trainer = Trainer(scene, cfg, device=args.device)
    print("| train s | views | PSNR | " + " | ".join(f"{k}: px / error share / PSNR" for k in REGIONS)
          + " | opacity on background |")
    print("| ---: | --- | ---: |" + " ---: |" * (len(REGIONS) + 1))
    for mark in marks:
        while trainer.train_seconds < mark:
            trainer.step(progress=trainer.train_seconds / cfg.seconds)
        for views, split, every in (("test", scene.test, 8), ("train", scene.train, 4)):
            r = error_regions(trainer, split, every)
            cells = [f"{r[k]['pixels']:.1%} / {r[k]['error']:.1%} / {r[k]['psnr']:.2f}" for k in REGIONS]
            print(f"| {mark:.0f} | {views} | {r['psnr']:.2f} | " + " | ".join(cells)
                  + f" | {r['background_opacity']:.4f} |", flush=True)


if __name__ == "__main__":
    main()
