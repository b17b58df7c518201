"""Where a view's floaters are: the weight each ray puts well in front of its surface.

    python benchmarks/floaters.py RUN_DIR [--view NAME] [--rays 65536] [--near-share 0.5]

For one held-out view (default: the run's worst in metrics.json) renders a random subset of its
pixels (one ray each, the mean appearance code) and splits each ray's weights at 0.8 × the
distance of its largest weight (the surface): the weight in front of it is "front" weight. Prints
how much of the view has front weight above 0.05 and 0.2, where along the rays it sits (as a
fraction of the surface distance and in world units), how far those points are from the
nearest training camera, how many training images hold them farther than the rays' near
distance (the training rays that reach them; lens distortion left out), and the largest
transmittance up to them from those images' cameras (near 0: each image that holds them shows a
surface in front of them, so no training pixel constrains them). Floaters hugging
training cameras point to near-camera fog (gradient scaling near cameras); floaters that no
training image holds, to space the field extrapolates into (the occupancy grid's visible cells
reach past the images' borders by up to a cell); floaters behind the surfaces of every image that
holds them, to occluded space; floaters mid-air in many images, to under-constrained space.

An opaque floater is its rays' surface and carries no front weight, so the same columns follow for
the rays whose surface lies nearer than ``--near-share`` of the view's median surface distance
(their t relative to that median), with the training images that hold most of those points: where
in the image, how far from the camera, and how clearly the camera sees them.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from fit_study import trainer_or_usage_error
from ngp_warp.data.cameras import generate_rays

TRANSMITTANCE_POINTS = 1024  # floater points whose training transmittance is measured


def ray_samples(trainer, rays_o: torch.Tensor, rays_d: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The samples of rays [R, 3] (origins, unit directions) through the trained field with its
    weight average: each sample's ray [S] int64, weight [S] float32 and midpoint distance [S]."""
    with torch.no_grad(), trainer.weights.averaged_in_field(), trainer.model.precision():
        out = trainer.model.render(rays_o, rays_d, trainer.field, background=1.0, return_samples=True)
    n = int(out["ray_offsets"][-1])
    return out["ray_indices"][:n], out["weights"][:n].float(), (0.5 * (out["t_starts"] + out["t_ends"]))[:n]


def front_weights(trainer, camera: dict, n_rays: int, seed: int = 0) -> dict:
    """Per ray (numpy): ``front`` weight, its weighted mean distance ``t_front``, ``t_surface``,
    and the front points and surface points [R, 3] in world space."""
    gen = torch.Generator().manual_seed(seed)
    w, h, dev = camera["width"], camera["height"], trainer.device
    px, py = torch.randint(0, w, (n_rays,), generator=gen).to(dev), torch.randint(0, h, (n_rays,), generator=gen).to(dev)
    dist = None if camera["distortion"] is None else camera["distortion"][None].expand(n_rays, 6).to(dev)
    rays_o, rays_d = generate_rays(camera["c2w"][None].expand(n_rays, 3, 4).to(dev),
                                   camera["intrinsics"][None].expand(n_rays, 4).to(dev), dist, px, py,
                                   fisheye=camera["fisheye"])
    ray, weight, t = ray_samples(trainer, rays_o, rays_d)
    best = torch.full((n_rays,), -1.0, device=dev).scatter_reduce(0, ray, weight, "amax")
    is_best = weight >= best[ray]
    t_surface = torch.zeros(n_rays, device=dev).scatter_reduce(0, ray[is_best], t[is_best], "amax", include_self=False)
    front = (t < 0.8 * t_surface[ray]).float() * weight
    front_sum = torch.zeros(n_rays, device=dev).index_add_(0, ray, front)
    t_front = torch.zeros(n_rays, device=dev).index_add_(0, ray, front * t) / front_sum.clamp_min(1e-8)
    points = rays_o + rays_d * t_front[:, None]
    surface_points = rays_o + rays_d * t_surface[:, None]
    return {k: v.cpu().numpy() for k, v in dict(front=front_sum, t_front=t_front, t_surface=t_surface,
                                                  points=points, surface_points=surface_points).items()}


def project(trainer, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each world point [P, 3] in each of the N training cameras (pinhole, lens distortion left
    out): pixel ``u``, ``v`` [P, N], distance [P, N] and whether the image holds it [P, N] bool
    (inside the image, in front of the camera and farther than the rays' near distance)."""
    split, near = trainer.scene.train, trainer.model.march.near
    c2w, k = split.c2w.double().numpy(), split.intrinsics.double().numpy()
    rel = points.astype(np.float64)[:, None, :] - c2w[None, :, :, 3]      # [P, N, 3]
    local = np.einsum("pnk,nkj->pnj", rel, c2w[:, :, :3])                 # camera frame (OpenGL)
    depth = np.maximum(-local[..., 2], 1e-12)
    u = k[None, :, 0] * local[..., 0] / depth + k[None, :, 2]
    v = k[None, :, 3] - k[None, :, 1] * local[..., 1] / depth
    distance = np.linalg.norm(rel, axis=-1)
    held = (-local[..., 2] > 0) & (distance > near)
    held &= (u >= 0) & (u <= split.width) & (v >= 0) & (v <= split.height)
    return u, v, distance, held


def training_transmittance(trainer, points: np.ndarray, held: np.ndarray) -> np.ndarray:
    """[P, N] float: the transmittance up to each world point [P, 3] along the ray from each
    training camera that holds it (``held`` [P, N] bool; 0 elsewhere). Near 0: the image shows a
    surface in front of the point, so its pixel does not constrain the point's density."""
    pair_point, pair_camera = np.nonzero(held)
    clear = np.zeros(held.shape, dtype=np.float32)
    if len(pair_point) == 0:
        return clear
    dev = trainer.device
    origins = trainer.scene.train.c2w[torch.from_numpy(pair_camera), :, 3].float().to(dev)
    offset = torch.from_numpy(points[pair_point]).float().to(dev) - origins
    distance = offset.norm(dim=-1)
    ray, weight, t = ray_samples(trainer, origins, offset / distance[:, None])
    before = torch.zeros(len(pair_point), device=dev).index_add_(0, ray, weight * (t < distance[ray]))
    clear[pair_point, pair_camera] = (1.0 - before).clamp(0, 1).cpu().numpy()
    return clear


def _fmt(q) -> str:
    return " / ".join(f"{v:.3f}" for v in q)


def print_row(trainer, label: str, points: np.ndarray, t: np.ndarray, t_rel: np.ndarray, share: float) -> None:
    """One table row for the points [P, 3] (P ≥ 1) at distances ``t`` [P] from the view's camera,
    ``t_rel`` [P] as a share of a surface distance (the ray's own, or the view's median), on
    ``share`` of the view's rays."""
    centres = trainer.scene.train.c2w[:, :, 3].cpu().numpy()
    near = np.linalg.norm(points[:, None] - centres[None], axis=-1).min(1)
    held = project(trainer, points)[3]
    some = points[:TRANSMITTANCE_POINTS]
    clear = training_transmittance(trainer, some, held[:TRANSMITTANCE_POINTS]).max(1)
    clear = clear[held[:TRANSMITTANCE_POINTS].any(1)]
    seen = f"{_fmt(np.percentile(clear, [10, 50, 90]))} | {(clear < 0.1).mean():.2f}" if len(clear) else "| "
    count = held.sum(1)
    print(f"| {label} | {share:.3f} | {_fmt(np.percentile(t_rel, [10, 50, 90]))} | {_fmt(np.percentile(t, [10, 50, 90]))} "
          f"| {_fmt(np.percentile(near, [10, 50, 90]))} | {' / '.join(f'{v:.0f}' for v in np.percentile(count, [10, 50, 90]))} "
          f"| {(count == 0).mean():.2f} | {seen} |")


def print_holders(trainer, points: np.ndarray, top: int = 6) -> None:
    """The training images that hold most of the points [P, 3]: how many, where in the image
    (median pixel), how far from their camera, and the transmittance up to them from it."""
    some = points[:TRANSMITTANCE_POINTS]
    u, v, distance, held = project(trainer, some)
    clear = training_transmittance(trainer, some, held)
    names = trainer.scene.train.names
    print("| training image | points held | median pixel (u, v) | distance (10/50/90 %) | transmittance (10/50/90 %) |")
    print("| --- | ---: | --- | --- | --- |")
    for n in np.argsort(-held.sum(0))[:top]:
        on = held[:, n]
        if not on.any():
            break
        print(f"| {Path(names[n]).name} | {on.sum()} | {np.median(u[on, n]):.0f}, {np.median(v[on, n]):.0f} | "
              f"{_fmt(np.percentile(distance[on, n], [10, 50, 90]))} | {_fmt(np.percentile(clear[on, n], [10, 50, 90]))} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run")
    ap.add_argument("--view", default=None, help="held-out image name (default: the worst in metrics.json)")
    ap.add_argument("--rays", type=int, default=65536)
    ap.add_argument("--near-share", type=float, default=0.5,
                    help="also report rays whose surface is nearer than this share of the view's median surface distance")
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
    print("| rays | share of rays | t / t_surface (10/50/90 %) | t (world) | to nearest training camera "
          "(10/50/90 %) | training images holding it (10/50/90 %) | held by none | training transmittance "
          "(10/50/90 %) | occluded in all (< 0.1) |")
    print("| --- | ---: | --- | --- | --- | --- | ---: | --- | ---: |")
    for level in (0.05, 0.2):
        sel = r["front"] > level
        if sel.any():
            print_row(trainer, f"front weight > {level}", r["points"][sel], r["t_front"][sel],
                      r["t_front"][sel] / np.maximum(r["t_surface"][sel], 1e-6), sel.mean())
    close = (r["t_surface"] > 0) & (r["t_surface"] < args.near_share * surface)
    if close.any():
        print_row(trainer, f"surface < {args.near_share:g} of the median", r["surface_points"][close],
                  r["t_surface"][close], r["t_surface"][close] / surface, close.mean())
        print(f"\nThe surfaces nearer than {args.near_share:g} of the median (opaque floaters) in the training images:")
        print_holders(trainer, r["surface_points"][close])


if __name__ == "__main__":
    main()
