"""Inference: whole images of a :class:`~ngp_warp.model.RadianceModel` from a camera, shared by
evaluation, orbit videos and viewers. The weights rendered are the field's own: a trainer swaps
its weight average in first (:meth:`ngp_warp.trainer.Trainer.render_image`)."""

from __future__ import annotations

import torch

from ngp_warp.cameras import generate_rays
from ngp_warp.model import RadianceModel


def subpixel_offsets(supersample: int) -> list[tuple[float, float]]:
    """The centres of a ``supersample`` × ``supersample`` grid of sub-pixels, as (dx, dy)
    offsets from the pixel centre in pixels, row by row."""
    k = supersample
    return [((a + 0.5) / k - 0.5, (b + 0.5) / k - 0.5) for b in range(k) for a in range(k)]


@torch.no_grad()
def render_view(model: RadianceModel, c2w: torch.Tensor, intrinsics: torch.Tensor, width: int, height: int, *,
                distortion: torch.Tensor | None = None, background: float = 1.0, chunk: int = 1 << 14,
                spp: int = 1, supersample: int = 1) -> dict:
    """Render one camera with the model's field in eval mode.

    Each pixel is the mean of ``supersample``² rays through its sub-pixel centres (the grid of
    the training pixels, see :class:`ngp_warp.config.TrainConfig`), each rendered ``spp``
    times with jittered sample offsets along the ray when ``spp`` > 1.

    Args:
        model: the scene's model (its field is switched to eval mode).
        c2w: [3, 4] float32 camera-to-world (OpenGL convention).
        intrinsics: [4] float32 fx, fy, cx, cy (pixels).
        width, height: image size in pixels.
        distortion: [4] float32 k1, k2, p1, p2 (OpenCV), or None for a pinhole.
        background: grey level blended behind the samples.
        chunk: pixels per render call (memory is one chunk's, whatever ``supersample`` and ``spp``).

    Returns:
        dict with ``rgb`` [H, W, 3] float32 in [0, 1], ``depth`` and ``opacity`` [H, W] float32.
    """
    if not (isinstance(spp, int) and spp >= 1):
        raise ValueError(f"spp must be a positive integer, got {spp!r}")
    model.field.eval()
    dev = model.device
    ys, xs = torch.meshgrid(torch.arange(height, device=dev), torch.arange(width, device=dev), indexing="ij")
    px, py = xs.reshape(-1), ys.reshape(-1)
    n = px.numel()
    c2w = c2w.to(dev).expand(n, 3, 4)
    intr = intrinsics.to(dev).expand(n, 4)
    dist = None if distortion is None else distortion.to(dev).expand(n, 4)
    bg = torch.full((3,), float(background), device=dev)
    parts = {"rgb": [], "depth": [], "opacity": []}
    shifts = subpixel_offsets(supersample)
    for lo in range(0, n, chunk):
        hi = min(n, lo + chunk)
        sums = dict.fromkeys(parts, 0.0)  # running sums: memory stays one render's whatever sub and spp
        for dx, dy in shifts:
            rays_o, rays_d = generate_rays(c2w[lo:hi], intr[lo:hi], None if dist is None else dist[lo:hi],
                                           px[lo:hi] + dx, py[lo:hi] + dy)
            for _ in range(spp):
                with model.precision():
                    out = model.render(rays_o, rays_d, model.field, background=bg, stratified=spp > 1)
                for k in parts:
                    sums[k] = sums[k] + out[k].float()
        for k in parts:
            parts[k].append(sums[k] / (len(shifts) * spp))
    return {
        "rgb": torch.cat(parts["rgb"]).reshape(height, width, 3).clamp(0, 1),
        "depth": torch.cat(parts["depth"]).reshape(height, width),
        "opacity": torch.cat(parts["opacity"]).reshape(height, width),
    }
