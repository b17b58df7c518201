"""How much of a held-out view's backdrop at infinity the training views show, and the best a
learned environment can do with it, on ``demo-colmap-sky`` (the demo object over the unbounded
scene's environment, as ``bench_captures.py`` writes it; about 5 minutes on 2 CPU cores).

    python benchmarks/backdrop_coverage.py [--steps 3000]

For every held-out frame (every 8th) prints: the share of its backdrop rays (alpha < 1 in the
source image) within 0.5° and 2° of some training ray; and the whole-image PSNR it would have
with a perfect object over (a) the field's environment model, sigmoid(W SH_4(d) + b), fitted to
the true environment along every training ray (the most a learned environment can know), and
(b) each ray's nearest training ray's backdrop colour. A view whose backdrop the training views
never saw is capped near (a) whatever the field does.
"""

from __future__ import annotations

import argparse
import math
import sys
import types
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))
import bench_captures  # noqa: E402
from capture_scenes import HELD_OUT_EVERY, ray_directions, synthetic_views  # noqa: E402
from ngp_warp.data.scene_unbounded import environment_colours  # noqa: E402
from ngp_warp.ops.spherical_harmonics import spherical_harmonics_deg4  # noqa: E402


def fit_environment(directions: torch.Tensor, colours: torch.Tensor, steps: int = 3000) -> torch.Tensor:
    """[16, 3] float32 W (the bias as SH band 0) minimising the mean squared error of
    sigmoid(SH_4(d) W) against ``colours`` [N, 3] along ``directions`` [N, 3] (Adam, lr 0.05)."""
    basis = spherical_harmonics_deg4(directions)
    weights = torch.zeros(basis.shape[1], 3, requires_grad=True)
    adam = torch.optim.Adam([weights], lr=0.05)
    for _ in range(steps):
        loss = (torch.sigmoid(basis @ weights) - colours).square().mean()
        adam.zero_grad()
        loss.backward()
        adam.step()
    return weights.detach()


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    """PSNR of ``a`` against ``b`` (values in [0, 1]); inf where they are equal."""
    mse = float((a - b).square().mean())
    return math.inf if mse == 0.0 else -10.0 * math.log10(mse)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/backdrop_coverage"), help="where the demo source is written")
    ap.add_argument("--steps", type=int, default=3000, help="Adam steps of the environment's fit")
    args = ap.parse_args()
    src = bench_captures.source("demo-colmap-sky", args.work, types.SimpleNamespace(lego=None, fox=None))
    views = synthetic_views(src)  # in the order bench_captures writes the capture
    rays, alphas = [], []
    for image, c2w, angle_x in views:
        rgba = iio.imread(image)
        height, width = rgba.shape[:2]
        focal = 0.5 * width / math.tan(0.5 * angle_x)
        rays.append(torch.from_numpy(ray_directions(c2w, width, height, focal).reshape(-1, 3)))
        alphas.append(torch.from_numpy(rgba[..., 3].reshape(-1).astype(np.float32) / 255.0)[:, None])
    held = [k for k in range(len(views)) if k % HELD_OUT_EVERY == 0]
    seen = torch.cat([rays[k] for k in range(len(views)) if k % HELD_OUT_EVERY != 0])
    weights = fit_environment(seen, environment_colours(seen), args.steps)
    print("| view | backdrop share | within 0.5° / 2° of a training ray | PSNR: fitted SH_4 environment | nearest training ray |")
    print("|---|---:|---:|---:|---:|")
    for k in held:
        d, alpha = rays[k], alphas[k]
        truth = environment_colours(d)
        cosine, index = (torch.cat(parts) for parts in zip(*((chunk @ seen.T).max(1) for chunk in d.split(2048))))
        angle = torch.rad2deg(torch.acos(cosine.clamp(-1.0, 1.0)))
        backdrop = alpha[:, 0] < 1.0
        fitted = torch.sigmoid(spherical_harmonics_deg4(d) @ weights)
        near = environment_colours(seen[index])
        # with a perfect object: the error is the backdrop's, weighted by 1 - alpha
        whole = [psnr((1.0 - alpha) * guess, (1.0 - alpha) * truth) for guess in (fitted, near)]
        print(f"| {k:04d} | {float(backdrop.float().mean()):.2f} | {float((angle[backdrop] < 0.5).float().mean()):.2f} / "
              f"{float((angle[backdrop] < 2.0).float().mean()):.2f} | {whole[0]:.1f} | {whole[1]:.1f} |")


if __name__ == "__main__":
    main()
