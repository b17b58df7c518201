"""Inference: whole images of a :class:`~ngp_warp.training.model.RadianceModel` from a camera, the one
fast path that evaluation, ``render`` videos, ``export`` and the viewer share. The weights
rendered are the field's own: a trainer swaps its weight average in first
(:meth:`ngp_warp.training.trainer.Trainer.render_image`).

What makes it fast, next to a training render of the same rays:

* no autograd at all (``torch.inference_mode``), the field in eval mode;
* the occupancy grid skips empty space (the march's DDA), and each marched sample is encoded
  at most once: the hash grid and density MLP (:meth:`~ngp_warp.ops.field.NGPField.geometry`, σ
  and the MLP's whole output h) run on each ray's first ``first_round`` marched samples, then
  on the rest of the samples of the rays whose transmittance after those is still ≥ half the
  model's ``early_stop_eps`` (early ray termination: samples behind an opaque surface are
  never encoded; the others get σ = 0, and as they lie behind the early-termination point
  nothing reads them). Only the samples in front of that point (transmittance ≥
  ``early_stop_eps``, :func:`ngp_warp.prune_samples`) take their h on through the colour
  network (:meth:`~ngp_warp.ops.field.NGPField.colour`). The image is a one-pass render's, up to
  the MLPs' rounding in batches of another size.
* the MLPs in the model's precision (bf16 on GPUs, :meth:`RadianceModel.precision`);
* rays are generated once per image (one launch per sub-pixel, :func:`ngp_warp.data.cameras.view_rays`,
  all sub-pixels' rays in one set), the outputs are written into buffers allocated once, and
  the chunks are as large as memory allows: their size adapts to the samples per ray of the
  chunks already rendered (:class:`ChunkSizer`), so a view takes a few chunks, each with two
  host synchronisations (the march's, the pruning's), four with the rounds.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import torch

from ngp_warp.data.cameras import view_rays
from ngp_warp.ops.composite import composite_packed
from ngp_warp.ops.gather import gather_rows, scatter_rows
from ngp_warp.training.model import RadianceModel
from ngp_warp.ops.prune import prune_samples
from ngp_warp.ops.raymarch import RaySamples, ray_marching

BYTES_PER_SAMPLE = 512  # device memory one marched sample needs through march, density and pruning
CPU_SAMPLE_BUDGET = 1 << 21  # marched samples per chunk on the CPU (a few hundred MB)
CUDA_SAMPLE_CAP = 1 << 25  # marched samples per chunk on CUDA at most (16 GiB)
MIN_CHUNK = 1 << 12  # rays
MAX_MARCHED_SHARE = 2  # a chunk that marches more than this × the sample budget is split: at the CUDA
                       # cap, 2^26 samples × a field's 16 levels (the default) still fit one hash-grid
                       # call (2^31 int32 items)


class ChunkSizer:
    """Rays per chunk from a budget of marched samples per chunk.

    The first chunk holds ``budget / first_guess`` rays; after each chunk the next holds
    ``budget / (1.5 × the most samples per ray seen so far)``, at least :data:`MIN_CHUNK`.
    :func:`render_view` guesses 1.5 × the last view's most samples per ray (64 for a model's
    first view), so a model's later views usually take one chunk on a large GPU.

    Args:
        sample_budget: marched samples a chunk may hold.
        first_guess: samples per ray assumed before any chunk was marched.
    """

    def __init__(self, sample_budget: int, first_guess: float = 64.0):
        self.sample_budget = int(sample_budget)
        self.samples_per_ray = float(first_guess) / 1.5

    def next_size(self, remaining: int) -> int:
        """Rays in the next chunk, ``remaining`` rays left: all of them when they are at most a
        quarter more than the budget's share (no small last chunk, whose syncs cost more than
        its work), else that share."""
        size = max(MIN_CHUNK, int(self.sample_budget / (1.5 * max(self.samples_per_ray, 1.0))))
        return remaining if remaining <= size + size // 4 else size

    def observe(self, n_rays: int, n_marched: int) -> None:
        if n_rays > 0:
            self.samples_per_ray = max(self.samples_per_ray, n_marched / n_rays)


def sample_budget(device: torch.device) -> int:
    """Marched samples one chunk may hold on ``device``: on CUDA half the free memory over
    :data:`BYTES_PER_SAMPLE`, at most :data:`CUDA_SAMPLE_CAP`; on the CPU :data:`CPU_SAMPLE_BUDGET`."""
    if device.type != "cuda":
        return CPU_SAMPLE_BUDGET
    free, _ = torch.cuda.mem_get_info(device)
    return max(1 << 16, min(CUDA_SAMPLE_CAP, free // 2 // BYTES_PER_SAMPLE))


def subpixel_offsets(supersample: int) -> list[tuple[float, float]]:
    """The centres of a ``supersample`` × ``supersample`` grid of sub-pixels, as (dx, dy)
    offsets from the pixel centre in pixels, row by row."""
    k = supersample
    return [((a + 0.5) / k - 0.5, (b + 0.5) / k - 0.5) for b in range(k) for a in range(k)]


def subpixel_rays(c2w: torch.Tensor, intrinsics: torch.Tensor, distortion: torch.Tensor | None, width: int,
                  height: int, device: torch.device, fisheye: bool, supersample: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Every ray of one camera (arguments as :func:`ngp_warp.data.cameras.view_rays`'s): origins and
    directions [supersample² × H × W, 3] float32, sub-pixel by sub-pixel (:func:`subpixel_offsets`),
    each row by row, in one set so that a supersampled view's chunks are as large as a plain one's."""
    # the camera on the device once, not once per sub-pixel: copying a host tensor waits for the device
    c2w, intrinsics = c2w.to(device, torch.float32), intrinsics.to(device, torch.float32)
    distortion = None if distortion is None else distortion.to(device, torch.float32)
    rays = [view_rays(c2w, intrinsics, distortion, width, height, device, fisheye, shift)
            for shift in subpixel_offsets(supersample)]
    return tuple(torch.cat(r) for r in zip(*rays)) if len(rays) > 1 else rays[0]


def _check_camera(c2w, intrinsics, distortion, width: int, height: int, spp: int, supersample: int,
                  fisheye: bool) -> None:
    for name, t, shape in (("c2w", c2w, (3, 4)), ("intrinsics", intrinsics, (4,))):
        if not isinstance(t, torch.Tensor) or tuple(t.shape) != shape:
            raise ValueError(f"{name} must be a {list(shape)} tensor, got {getattr(t, 'shape', type(t).__name__)}")
    if distortion is not None and (not isinstance(distortion, torch.Tensor) or tuple(distortion.shape) != (6,)):
        raise ValueError(f"distortion must be None or a [6] tensor (k1 k2 k3 k4 p1 p2), "
                         f"got {getattr(distortion, 'shape', type(distortion).__name__)}")
    if fisheye and distortion is None:
        raise ValueError("a fisheye view needs its distortion (zeros for the plain equidistant lens)")
    for name, value in (("width", width), ("height", height), ("spp", spp), ("supersample", supersample)):
        if not (isinstance(value, int) and value >= 1):
            raise ValueError(f"{name} must be a positive integer, got {value!r}")


def _marched_rows(marched_offsets: torch.Tensor, kept: RaySamples) -> torch.Tensor:
    """The row among the marched samples of each kept sample, [S] int64. prune_samples keeps a
    prefix of each ray's samples (front to back, no capacity: no padding), so kept row j of ray
    r is marched row ``marched_offsets[r] + j - kept.ray_offsets[r]``.

    marched_offsets: [n_rays + 1] int32 offsets of the marched samples. kept: the pruned samples.
    """
    shift = (marched_offsets[:-1] - kept.ray_offsets[:-1]).long()
    return gather_rows(shift, kept.ray_indices) + torch.arange(kept.n_samples, device=shift.device)


FIRST_ROUND = 16  # render_view's first round before any view (and its least)


def auto_first_round(shaded_per_ray: float | None) -> int:
    """``first_round`` from the mean samples per ray the model's last view shaded (None before
    any view): 1.5 times that, rounded up to a multiple of 8, at least :data:`FIRST_ROUND`. On
    an H200 (RESULTS.md) lego (5.2 shaded per ray) rendered fastest with 16 and fox
    (20.1) with 32 of the values tried."""
    if shaded_per_ray is None:
        return FIRST_ROUND
    return max(FIRST_ROUND, 8 * math.ceil(1.5 * shaded_per_ray / 8))


def _geometry(field, samples: RaySamples, eps: float, first_round: int | None):
    """σ [S] float32 and h [S, G] of the S marched samples, in one pass, or in two rounds (see
    the module) when ``first_round`` is set, ``eps`` is positive in float32 (as the pruning
    compares it) and the chunk holds more than ``first_round`` samples per ray on average. Rows
    never encoded have σ = 0 and unset h. Also returns the host int rows encoded."""
    n_rays, n_samples = samples.ray_offsets.shape[0] - 1, samples.n_samples
    eps = float(torch.tensor(eps, dtype=torch.float32))
    if first_round is None or eps <= 0 or n_samples <= n_rays * first_round:
        return (*field.geometry(samples.positions), n_samples)
    rays = samples.ray_indices
    in_ray = torch.arange(n_samples, device=rays.device) - gather_rows(samples.ray_offsets, rays)
    front = in_ray < first_round
    rows = front.nonzero().squeeze(1)  # a host sync, as is the next nonzero
    sigma = torch.zeros(n_samples, device=rays.device)
    sigma_front, h_front = field.geometry(gather_rows(samples.positions, rows))
    h = h_front.new_empty(n_samples, h_front.shape[1])
    scatter_rows(sigma, rows, sigma_front)
    scatter_rows(h, rows, h_front)
    lengths = gather_rows(samples.t_ends, rows) - gather_rows(samples.t_starts, rows)
    optical_depth = torch.zeros(n_rays, device=rays.device).index_add_(0, gather_rows(rays, rows), sigma_front * lengths)
    alive = optical_depth < -math.log(eps / 2)  # half eps: prune's own rounding cannot keep an unset row
    rest = (~front & alive[rays]).nonzero().squeeze(1)
    if rest.numel() > 0:
        sigma_rest, h_rest = field.geometry(gather_rows(samples.positions, rest))
        scatter_rows(sigma, rest, sigma_rest)
        scatter_rows(h, rest, h_rest)
    return sigma, h, rows.numel() + rest.numel()


def _render_chunk(model: RadianceModel, rays_o: torch.Tensor, rays_d: torch.Tensor, bg: torch.Tensor | None,
                  stratified: bool, codes: list[torch.Tensor | None], first_round: int | None,
                  max_marched: int) -> dict:
    """One chunk of N rays (see the module): march, σ and h of the marched samples (:func:`_geometry`),
    prune, then for each of the K ``codes`` (resolved [A] codes, or [None] without appearance
    codes) the colour MLP on the kept samples' h and the composite over ``bg`` [3] (None: the
    field's environment along each ray).

    Returns ``rgb`` [K, N, 3], ``opacity`` [N], ``depth`` [N] float32 and host ints
    ``n_marched``, ``n_encoded`` (through the density MLP), ``n_shaded`` (through the colour MLP,
    per code); only ``n_marched`` (then ``max_marched`` + 1: the march stops counting there)
    when the chunk holds more than one ray and marched more than ``max_marched`` samples (the
    caller renders fewer rays at a time).
    """
    field, eps, n_rays = model.field, model.early_stop_eps, rays_o.shape[0]
    march = model.march_options(stratified)
    if n_rays > 1:  # the count past max_marched only tells that the chunk is dropped: no room for it
        cut = max_marched + 1 if march.max_samples is None else min(march.max_samples, max_marched + 1)
        march = dataclasses.replace(march, max_samples=cut)
    samples = ray_marching(rays_o, rays_d, model.grid, march, validate=False)
    if samples.n_samples > max_marched and n_rays > 1:
        return {"n_marched": samples.n_samples}
    bg = field.background(rays_d) if bg is None else bg
    out = {"rgb": bg.expand(len(codes), n_rays, 3).clone(), "opacity": torch.zeros(n_rays, device=rays_o.device),
           "depth": torch.zeros(n_rays, device=rays_o.device), "n_marched": samples.n_samples, "n_encoded": 0,
           "n_shaded": 0}
    if samples.n_samples == 0:
        return out
    with model.precision():
        sigma, h, out["n_encoded"] = _geometry(field, samples, eps, first_round)
        kept = prune_samples(samples, sigma, eps).samples
        out["n_shaded"] = kept.n_samples
        if kept.n_samples == 0:  # early_stop_eps > 1: nothing composites
            return out
        rows = _marched_rows(samples.ray_offsets, kept)
        kept_h, kept_sigma = gather_rows(h, rows), gather_rows(sigma, rows)
        for k, code in enumerate(codes):  # σ does not depend on the code: opacity and depth come out the same
            rgbs = field.colour(kept_h, kept.directions, code)
            rgb, out["opacity"], out["depth"], _ = composite_packed(kept_sigma, rgbs, kept.t_starts, kept.t_ends,
                                                                    kept.ray_offsets, eps)
            out["rgb"][k] = rgb + bg * (1.0 - out["opacity"])[:, None]
    return out


def _render_rays(model: RadianceModel, rays_o: torch.Tensor, rays_d: torch.Tensor, bg: torch.Tensor | None,
                 spp: int, codes: list[torch.Tensor | None], first_round: int | None, chunk_size,
                 sizer: ChunkSizer | None):
    """Rays [R, 3] rendered ``spp`` times in chunks of ``chunk_size(remaining rays)`` rays
    (:func:`_render_chunk`, coloured with each of the K ``codes``) → rgb [K, R, 3], depth [R],
    opacity [R] summed over the ``spp`` renders, and the host counts summed likewise; ``sizer``
    (when given) observes every chunk. A chunk whose rays march more samples than
    :data:`MAX_MARCHED_SHARE` × the device's :func:`sample_budget` (a first guess far below a
    barely trained field's samples per ray) is dropped, and no later chunk holds more than half
    its rays (with a sizer, usually fewer)."""
    total, dev = rays_o.shape[0], rays_o.device
    rgb, depth = torch.zeros(len(codes), total, 3, device=dev), torch.zeros(total, device=dev)
    opacity = torch.zeros(total, device=dev)
    counts = {"n_marched": 0, "n_encoded": 0, "n_shaded": 0}
    max_marched, most_rays = MAX_MARCHED_SHARE * (sizer.sample_budget if sizer else sample_budget(dev)), total
    for _ in range(spp):
        lo = 0
        while lo < total:
            hi = min(total, lo + chunk_size(total - lo), lo + most_rays)
            out = _render_chunk(model, rays_o[lo:hi], rays_d[lo:hi], bg, spp > 1, codes, first_round, max_marched)
            if sizer is not None:
                sizer.observe(hi - lo, out["n_marched"])
            if "rgb" not in out:  # too many samples for one chunk: half as many rays
                most_rays = (hi - lo) // 2
                continue
            rgb[:, lo:hi] += out["rgb"]
            depth[lo:hi] += out["depth"]
            opacity[lo:hi] += out["opacity"]
            for key in counts:
                counts[key] += out[key]
            lo = hi
    return rgb, depth, opacity, counts


@torch.inference_mode()
def render_view(model: RadianceModel, c2w: torch.Tensor, intrinsics: torch.Tensor, width: int, height: int, *,
                distortion: torch.Tensor | None = None, fisheye: bool = False, background: float | None = 1.0,
                chunk: int | None = None, spp: int = 1, supersample: int = 1,
                appearance_code: torch.Tensor | None = None, other_codes: Sequence[torch.Tensor | None] = (),
                first_round: int | str | None = "auto") -> dict:
    """Render one camera with the model's field in eval mode.

    Each pixel is the mean of ``supersample``² rays through its sub-pixel centres (the grid of
    the training pixels, see :class:`ngp_warp.training.config.TrainConfig`), each rendered ``spp``
    times with jittered sample offsets along the ray when ``spp`` > 1.

    Args:
        model: the scene's model (its field is switched to eval mode).
        c2w: [3, 4] float32 camera-to-world (OpenGL convention).
        intrinsics: [4] float32 fx, fy, cx, cy (pixels).
        width, height: image size in pixels.
        distortion: [6] float32 k1, k2, k3, k4, p1, p2 (OpenCV), or None for a pinhole.
        fisheye: the lens is OpenCV's fisheye (``distortion`` required).
        background: grey level blended behind the samples; None: the field's learned
            environment along each ray (:meth:`ngp_warp.ops.field.NGPField.background`).
        chunk: rays per chunk; None sizes chunks to the device's memory (:class:`ChunkSizer`).
            The image does not depend on it.
        appearance_code: [A] float32 appearance code for every ray (e.g. one fitted to a test
            view); None: the mean training code. Only for fields with appearance codes.
        other_codes: more codes ([A] float32 each, or None for the mean code) to colour the same
            samples with: the view as each would render it, at the cost of one colour MLP and
            composite each (σ does not depend on the code). Only for fields with appearance codes.
        first_round: samples per ray encoded before the rays that are already opaque stop (see
            the module); None encodes every marched sample at once; ``"auto"``
            (:func:`auto_first_round`) takes it from the model's last view. Speed only: the
            image changes by no more than the MLPs' rounding.

    Returns:
        dict with ``rgb`` [H, W, 3] float32 in [0, 1], ``depth`` and ``opacity`` [H, W] float32
        (depth is Σ w t: divide by opacity for the surface distance), and host ints
        ``n_marched`` (samples marched), ``n_encoded`` (through the hash grid and density MLP) and
        ``n_shaded`` (through the colour network, per code); with ``other_codes``,
        ``other_rgb`` [K, H, W, 3] float32, the view coloured with each of them.
    """
    _check_camera(c2w, intrinsics, distortion, width, height, spp, supersample, fisheye)
    for name, value in (("chunk", chunk), ("first_round", None if first_round == "auto" else first_round)):
        if value is not None and not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
            raise ValueError(f"{name} must be None or a positive integer{', or auto' * (name == 'first_round')}, "
                             f"got {value!r}")
    if first_round == "auto":
        first_round = auto_first_round(model.view_shaded_per_ray)
    if other_codes and model.field.appearance is None:
        raise ValueError("other_codes given, but this field has no appearance codes (appearance_dim 0)")
    codes = [model.field.appearance_code(c) for c in (appearance_code, *other_codes)]
    if model.field.training:
        model.field.eval()
    dev = model.device
    n = width * height
    if background is None and model.field.environment is None:
        raise ValueError("background None renders the field's environment, but this field has none")
    bg = None if background is None else torch.full((3,), float(background), device=dev)
    sizer = None if chunk is not None else ChunkSizer(
        sample_budget(dev), 1.5 * model.view_samples_per_ray if model.view_samples_per_ray else 64.0)
    rays_o, rays_d = subpixel_rays(c2w, intrinsics, distortion, width, height, dev, fisheye, supersample)
    rgb, depth, opacity, counts = _render_rays(model, rays_o, rays_d, bg, spp, codes, first_round,
                                               lambda remaining: chunk or sizer.next_size(remaining), sizer)
    if sizer is not None:
        model.view_samples_per_ray = sizer.samples_per_ray
    model.view_shaded_per_ray = counts["n_shaded"] / (rays_o.shape[0] * spp)
    scale = 1.0 / (supersample**2 * spp)
    rgb = rgb.view(len(codes), -1, n, 3).sum(1).mul_(scale).clamp_(0, 1).reshape(len(codes), height, width, 3)
    return {
        "rgb": rgb[0],
        "depth": depth.view(-1, n).sum(0).mul_(scale).reshape(height, width),
        "opacity": opacity.view(-1, n).sum(0).mul_(scale).reshape(height, width),
        **counts,
        **({"other_rgb": rgb[1:]} if other_codes else {}),
    }

