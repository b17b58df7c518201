"""Which appearance code suits a held-out view: one trained run's test views rendered with
several codes and scored on the whole image and on each half.

    python benchmarks/code_choice.py RUN_DIR [--device DEVICE]

Codes: the nearest training camera's (what metrics.json's ``psnr_nearest_code`` uses), the mean
of the two nearest, the three nearest weighted by inverse distance, the mean of all training
codes, and the code fitted on the view's own left half
(:func:`ngp_warp.training.appearance_fit.fit_appearance_code`) from the mean code (what
metrics.json's ``psnr`` uses) and from the nearest camera's, and of these two fits the one
that scores higher on the left half (a choice made on the pixels the fit sees). If the right half with the
nearest code scores what it scores with the fitted code, the held-out views' code is not what
limits the whole image; the field is. Prints a table: per view and the mean (PSNR in dB).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from ngp_warp.outputs.evaluate import psnr_whole_and_halves
from ngp_warp.training.appearance_fit import fit_appearance_code

sys.path.insert(0, str(Path(__file__).parent))
from fit_study import held_out_views, trainer_or_usage_error  # noqa: E402

CHOICES = ("nearest", "two nearest", "three nearest, 1/d", "mean", "fitted on the left half",
           "fitted on the left half from the nearest", "the fit that scores higher on the left half")


def candidate_codes(codes: torch.Tensor, centres: torch.Tensor, centre: torch.Tensor) -> list[torch.Tensor]:
    """The codes of :data:`CHOICES` but the fitted ones, each [A] float32, for a view whose camera
    centre is ``centre`` ([3]); ``codes`` [N, A] and ``centres`` [N, 3] are the training images'."""
    distance = (centres - centre).norm(dim=-1)
    order = distance.argsort()
    inverse = 1.0 / distance[order[:3]].clamp_min(1e-9)
    return [codes[order[0]], codes[order[:2]].mean(0), (codes[order[:3]] * (inverse / inverse.sum())[:, None]).sum(0),
            codes.mean(0)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run", help="a finished run's folder (its checkpoint.pt)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = parser.parse_args()
    trainer = trainer_or_usage_error(parser, args.run, args.device, need_codes=True)
    codes = trainer.field.appearance.weight.detach()
    centres = trainer.train_split.c2w[:, :, 3].to(codes.device)
    background = trainer.view_background
    rows = []
    for name, camera, gt in held_out_views(trainer):
        choices = candidate_codes(codes, centres, camera["c2w"][:3, 3].to(centres))
        choices.append(fit_appearance_code(trainer, **camera, image=gt, background=background))
        choices.append(fit_appearance_code(trainer, **camera, image=gt, background=background, start=choices[0]))
        renders = [trainer.render_image(**camera, background=background, appearance_code=code)["rgb"]
                   for code in choices]
        scores = [psnr_whole_and_halves(rgb, gt) for rgb in renders]
        scores.append(max(scores[-2:], key=lambda whole_left_right: whole_left_right[1]))  # chosen on what the fit saw
        rows.append(scores)
        print(Path(name).name, "  ".join(f"{c}: {w:.2f}/{l:.2f}/{r:.2f}" for c, (w, l, r) in zip(CHOICES, scores)),
              flush=True)
    mean = np.mean(np.array(rows), axis=0)
    print("\n| code | whole | left half | right half |\n|---|---:|---:|---:|")
    for choice, (whole, left, right) in zip(CHOICES, mean):
        print(f"| {choice} | {whole:.2f} | {left:.2f} | {right:.2f} |")


if __name__ == "__main__":
    main()
