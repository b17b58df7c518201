"""Where a view's floaters are: the weight each ray puts well in front of its surface.

    python benchmarks/floaters.py RUN_DIR [--view NAME] [--rays 65536]

For one held-out view (default: the run's worst in metrics.json) renders a random subset of its
pixels (one ray each, the mean appearance code) and splits each ray's weights at 0.8 × the
distance of its largest weight (the surface): the weight in front of it is "front" weight. Prints
how much of the view has front weight above 0.05 and 0.2, where along the rays it sits (as a
fraction of the surface distance and in world units), how far those points are from the
nearest training camera, and how many training images hold them farther than the rays' near
distance (the training rays that reach them; lens distortion left out). Floaters hugging
training cameras point to near-camera fog (gradient scaling near cameras); floaters that no
training image holds, to space the field extrapolates into (the occupancy grid's visible cells
reach past the images' borders by up to a cell); floaters mid-air in many images, to
under-constrained space.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from fit_study import trainer_or_usage_error
from ngp_warp.data.cameras import generate_rays


def front_weights(trainer, camera: dict, n_rays: int, seed: int = 0) -> dict:
    """Per ray (numpy): ``front`` weight, its weighted mean distance ``t_front``, ``t_surface``,
    and the front points [R, 3] in world space."""
    gen = torch.Generator().manual_seed(seed)
    w, h, dev = camera["width"], camera["height"], trainer.device
    px, py = torch.randint(0, w, (n_rays,), generator=gen).to(dev), torch.randint(0, h, (n_rays,), generator=gen).to(dev)
    dist = None if camera["distortion"] is None else camera["distortion"][None].expand(n_rays, 6).to(dev)
    rays_o, rays_d = generate_rays(camera["c2w"][None].expand(n_rays, 3, 4).to(dev),
                                   camera["intrinsics"][None].expand(n_rays, 4).to(dev), dist, px, py,
                                   fisheye=camera["fisheye"])
    with torch.no_grad(), trainer.weights.averaged_in_field(), trainer.model.precision():
        out = trainer.model.render(rays_o, rays_d, trainer.field, background=1.0, return_samples=True)
    n = int(out["ray_offsets"][-1])
    ray, weight = out["ray_indices"][:n], out["weights"][:n].float()
    t = (0.5 * (out["t_starts"] + out["t_ends"]))[:n]
    best = torch.full((n_rays,), -1.0, device=dev).scatter_reduce(0, ray, weight, "amax")
    is_best = weight >= best[ray]
    t_surface = torch.zeros(n_rays, device=dev).scatter_reduce(0, ray[is_best], t[is_best], "amax", include_self=False)
    front = (t < 0.8 * t_surface[ray]).float() * weight
    front_sum = torch.zeros(n_rays, device=dev).index_add_(0, ray, front)
    t_front = torch.zeros(n_rays, device=dev).index_add_(0, ray, front * t) / front_sum.clamp_min(1e-8)
    points = rays_o + rays_d * t_front[:, None]
    return {k: v.cpu().numpy() for k, v in dict(front=front_sum, t_front=t_front, t_surface=t_surface,
                                                  points=points).items()}


def training_images_holding(trainer, points: np.ndarray) -> np.ndarray:
    """[P] int: how many training images hold each world point [P, 3] (pinhole projection inside
    the image, in front of the camera and farther than the rays' near distance from it)."""
    split, near = trainer.scene.train, trainer.model.march.near
    c2w, k = split.c2w.double().numpy(), split.intrinsics.double().numpy()
    rel = points.astype(np.float64)[:, None, :] - c2w[None, :, :, 3]      # [P, N, 3]
    local = np.einsum("pnk,nkj->pnj", rel, c2w[:, :, :3])                 # camera frame (OpenGL)
    depth = np.maximum(-local[..., 2], 1e-12)
    u = k[None, :, 0] * local[..., 0] / depth + k[None, :, 2]
    v = k[None, :, 3] - k[None, :, 1] * local[..., 1] / depth
    held = (-local[..., 2] > 0) & (np.linalg.norm(rel, axis=-1) > near)
    held &= (u >= 0) & (u <= split.width) & (v >= 0) & (v <= split.height)
    return held.sum(1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run")
    ap.add_argument("--view", default=None, help="held-out image name (default: the worst in metrics.json)")
    ap.add_argument("--rays", type=int, default=65536)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = ap.parse_args()
    trainer = trainer_or_usage_error(ap, args.run, args.device)
    split = trainer.scene.test
    names = [Path(n).name for n in split.names]
    view = args.view
    if view is None:
        per_image = json.loads((Path(args.run) / "metrics.json").read_text())["per_image"]
        view = Path(min(per_image, key=lambda v: v["psnr"])["image"]).name
    if view not in names:
        ap.error(f"no held-out view {view!r}; the views are {', '.join(names)}")
    camera = split.camera(names.index(view))
    r = front_weights(trainer, camera, args.rays)
    centres = trainer.scene.train.c2w[:, :, 3].cpu().numpy()
    own = camera["c2w"][:, 3].cpu().numpy()
    surface = np.median(r["t_surface"][r["t_surface"] > 0])
    print(f"view {view}: median surface distance {surface:.3f}; nearest training camera "
          f"{np.linalg.norm(centres - own, axis=1).min():.3f} from this camera")
    print("| front weight > | share of rays | t / t_surface (10/50/90 %) | t (world) | to nearest training camera "
          "(10/50/90 %) | training images holding it (10/50/90 %) | held by none |")
    print("| ---: | ---: | --- | --- | --- | --- | ---: |")
    for level in (0.05, 0.2):
        sel = r["front"] > level
        if not sel.any():
            print(f"| {level} | 0 | | | | | |")
            continue
        rel = np.percentile(r["t_front"][sel] / np.maximum(r["t_surface"][sel], 1e-6), [10, 50, 90])
        tw = np.percentile(r["t_front"][sel], [10, 50, 90])
        near = np.linalg.norm(r["points"][sel][:, None] - centres[None], axis=-1).min(1)
        nq = np.percentile(near, [10, 50, 90])
        held = training_images_holding(trainer, r["points"][sel])
        fmt = lambda q: " / ".join(f"{v:.3f}" for v in q)  # noqa: E731
        print(f"| {level} | {sel.mean():.3f} | {fmt(rel)} | {fmt(tw)} | {fmt(nq)} | "
              f"{' / '.join(f'{v:.0f}' for v in np.percentile(held, [10, 50, 90]))} | {(held == 0).mean():.2f} |")


if __name__ == "__main__":
    main()
