"""Per-scene defaults of the march and the field: cone steps, contraction, appearance codes, the
learned environment's starting colour.

* Cone steps (instant-ngp's ``calc_dt``): scenes larger than the unit box (``aabb_scale`` > 1,
  i.e. more than one occupancy cascade) and unbounded scenes step by
  ``Δt = clamp(t / 256, √3/1024, √3)`` in instant-ngp unit-cube lengths: the finest cascade's
  box diagonal / 1024 up to that whole diagonal (instant-ngp's ``MIN_CONE_STEPSIZE`` and
  ``MAX_CONE_STEPSIZE`` with its 8 cascades of 128³ cells). NeRF-synthetic scenes keep fixed steps.
* Contraction: the files' ``contraction`` key, else mip-NeRF 360's L2 contraction for captures
  (not NeRF-synthetic) whose cameras surround a centre and look inward
  (:func:`cameras_surround_centre`) and whose images show more than a plain backdrop
  (:func:`plain_backdrop`), else none. Its inner box is the finest cascade's box, grown about
  its centre to hold every training camera (``contraction_fit`` "seen": to what the median
  camera sees); the field learns the colour at infinity (``FieldConfig.environment``). Where
  this rule contracts, ``contraction_fit`` "auto" (the default, where a run can train a probe)
  and "probe" tell by a short training an object before a distant backdrop, which then trains
  bounded in a box of 32 with a learned colour at infinity, from a scene with content around its
  cameras, which trains contracted
  (:mod:`ngp_warp.training.contraction_probe`).
* Field box: a COLMAP capture of an object on a plain backdrop that trains bounded gets the box
  its cameras see (:func:`choose_aabb_scale`), not the one holding its cameras.
* Occupancy threshold: instant-ngp's 0.01 (optical thickness of one step) on NeRF-synthetic
  renders; 0.05 on captures. On fox (H200, 60 s, RESULTS.md) 0.01 left 60 % of the
  finest cascade's visible cells occupied: 67 trained samples per ray (median), about 4k rays
  per step; 0.05 took it to 25 per ray and 10k rays per step at the same held-out PSNR
  (28.21 → 27.7–28.0 dB, mean code), while lego at 0.05 stayed within 0.05 dB.
* Near distance: a bounded capture whose pinhole cameras converge on one point
  (:func:`focus_distance`: a walk around a subject, part of one, or a converging forward-facing
  set) starts its rays 0.3 of the cameras' median distance to that point from each camera (fox:
  1.52 against the files' 0.30), or at the scene's own near if larger. Density closer to a
  camera than that is seen by few other cameras, and there the field grows the floaters that
  held-out views near a training camera see. On fox (H200, 60 s, RESULTS.md) it scored 30.53 dB
  over ten runs, +0.31 to +0.67 dB on each of four seeds paired with the files' near (mean
  +0.47), with no collapsed view and 17 in place of 24 trained samples per ray; the other
  bounded capture scenes moved within their runs' spread (−0.2 to +0.3 dB), the objects over
  the sky gained. Contracted scenes, NeRF-synthetic renders and fisheye captures keep the
  scene's near.
* The start of a bounded capture on CUDA: until the batches have met about 5 % of the training
  pixels (at most 1000 steps), the learning rate warms up and the occupancy grid culls no
  visible cell; such a run's grid refreshes also count density only where a training ray can
  sample (``grid_seen_only``), for the whole run. A capture whose 5 % takes 100 steps or fewer
  starts as every other run (a 100-step warm-up, every point's density). Early in a high-resolution capture's training, when the batches have
  met a few per cent of its pixels, the finest levels can put an opaque blob just past a few
  training cameras' near for some images' rows, which held-out views near them see (fox's
  view 0012 at 16–27 dB, in about one run of five); the slow start keeps it away, and the open
  grid keeps the soft early field from culling weakly seen space that it cannot win back (fox's
  view 0001, at the capture's edge). On fox (43 images of 1080 × 1920: 1000 steps; H200, 60 s,
  RESULTS.md) the right halves scored 32.09 over ten runs, each 31.95–32.26, against 31.72 on
  seven of the seeds with the warm-up alone and about 31.7 with neither; six more runs at this
  rule scored 32.17. The lego capture forms (400 × 400: 256 steps) scored 0.06–0.31 dB over a
  100-step start. A small-image capture meets each pixel hundreds of times in a run, and there
  a 1000-step start cost 0.5 dB (the demo object as a COLMAP model, 52 images of 100 × 100,
  whose 5 % takes under 100 steps: it starts as every other run). A CPU run's whole budget is a
  few thousand steps, and the seen-only count is costly there, so CPU runs start as every other
  run.
* Appearance codes: 16 per training image for captures (exposure and white balance vary),
  none for NeRF-synthetic renders.
* Distortion loss (mip-NeRF 360), in its normalised distance s = 1 − near/t: weight 4e-3 on
  bounded captures, 0 elsewhere. On fox (H200, 60 s, RESULTS.md) the loss thins the
  semi-transparent floaters in front of the training cameras that some held-out views see
  (7.6 → 2 % of view 0089's rays): none 30.28 dB (five seeds), world-space 1e-4 31.09 (eight),
  normalised 4e-3 31.27 (eight). World-space 5e-4 put more weight in front (29.45
  over five). On the contracted unbounded scene world-space 1e-4 cost about 2.5 dB and
  normalised 4e-3 neither cost nor gained (runs there differ by up to 5 dB), so it stays off.
"""

from __future__ import annotations

import math

import torch

from ngp_warp.data.loading import Scene
from ngp_warp.data.scene_normalisation import MIN_SPREAD, axes_focus
from ngp_warp.data.transforms_json import CONTRACTIONS

CONE_ANGLE = 1.0 / 256.0  # instant-ngp's cone angle for aabb_scale > 1
SYNTHETIC_OCCUPANCY_THRESHOLD = 0.01  # instant-ngp's NERF_MIN_OPTICAL_THICKNESS
CAPTURE_OCCUPANCY_THRESHOLD = 0.05
APPEARANCE_DIM = 16
CAPTURE_DISTORTION_WEIGHT = 4e-3  # with distortion_spacing 'normalised'
_MIN_CAMERAS = 8  # fewer cameras never count as surrounding a centre
_MAX_RESULTANT = 0.5  # |mean horizontal direction from the centre to the cameras|: 0 for a ring
_MIN_INWARD = 0.8  # mean cosine between a camera's view axis and its direction to the centre
CAPTURE_WARMUP_STEPS = 1000  # the longest start of a bounded capture on CUDA (warm-up and open grid)
START_PIXEL_SHARE = 0.05  # ... which lasts until the batches have met this share of the training pixels
NOMINAL_SAMPLES_PER_RAY = 16  # trained samples a ray, to count a step's pixels before training (fox: 15-17)
WARMUP_STEPS = 100  # every other run's learning-rate warm-up
FOCUS_NEAR_SHARE = 0.3  # a bounded capture's rays start this share of the cameras' distance to their focus
_BACKDROP_SHARE = 0.98  # share of the images' edge pixels within _BACKDROP_TOLERANCE of one colour
_BACKDROP_TOLERANCE = 8  # in 8-bit levels, per channel
CONTRACTION_FITS = ("cameras", "seen")  # what the contraction's inner box is grown to hold
PROBE_FIT = "probe"  # bounded or "cameras", picked by a short training (ngp_warp.training.contraction_probe)
AUTO_FIT = "auto"  # the probe where the scene's own rule contracts and the run can train one, else "cameras"


def cone_steps(scene: Scene, contraction: str | None) -> tuple[float, float, float]:
    """(cone_angle, min step, max step) in world lengths for ``scene``: (0, √3/1024·L, √3·L)
    for one cascade without contraction, else (1/256, ...), L the finest cascade box's side."""
    box = scene.occupancy_aabb.double()
    diagonal = float((box[3:] - box[:3]).norm())
    cone = CONE_ANGLE if scene.occupancy_levels > 1 or contraction is not None else 0.0
    return cone, diagonal / 1024.0, diagonal


def _focus(c2w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, float]:
    """For ``c2w`` [N, 3, 4] float (OpenGL: looking down −z): the point q [3] nearest every view
    axis (least squares), the cameras' centres [N, 3] and view axes [N, 3], float64, and the
    smallest eigenvalue of mean(I − f fᵀ) (near 0 where the axes are parallel and q is unsettled)."""
    m = c2w.double().cpu()
    centres, forward = m[:, :, 3], -torch.nn.functional.normalize(m[:, :, 2], dim=-1)
    q, spread = axes_focus(centres.numpy(), forward.numpy())
    return torch.from_numpy(q), centres, forward, spread


def _inward(q: torch.Tensor, centres: torch.Tensor, forward: torch.Tensor) -> float:
    """Mean cosine between each camera's view axis and its direction to ``q``."""
    return float(-(torch.nn.functional.normalize(centres - q, dim=-1) * forward).sum(-1).mean())


def cameras_surround_centre(c2w: torch.Tensor) -> bool:
    """Whether the cameras (``c2w`` [N, 3, 4] float, OpenGL: looking down −z) form a 360° capture:
    at least 8 cameras; their centre q (the point nearest every view axis, least squares);
    seen from q, the cameras' directions projected on the plane normal to the mean camera up
    axis nearly cancel (mean vector shorter than 0.5; a full ring gives 0, a half circle
    2/π ≈ 0.64); and they look at q (mean cosine between view axis and direction to q ≥ 0.8)."""
    if c2w.shape[0] < _MIN_CAMERAS:
        return False
    q, centres, forward, _ = _focus(c2w)
    outward = torch.nn.functional.normalize(centres - q, dim=-1)
    up = torch.nn.functional.normalize(c2w[:, :, 1].double().cpu().mean(0), dim=0)
    flat = torch.nn.functional.normalize(outward - (outward @ up)[:, None] * up, dim=-1)
    return _inward(q, centres, forward) >= _MIN_INWARD and float(flat.mean(0).norm()) < _MAX_RESULTANT


def focus_distance(c2w: torch.Tensor) -> float | None:
    """The training cameras' (``c2w`` [N, 3, 4] float) median distance to the point they all look
    at, or None unless at least 8 cameras converge on one: their view axes spread (smallest
    eigenvalue of mean(I − f fᵀ) above 0.01, about 6°, as the scene normalisation asks) and they
    look at that point (mean cosine ≥ 0.8), as a walk around a subject does (half rings and
    converging forward-facing sets too)."""
    if c2w.shape[0] < _MIN_CAMERAS:
        return None
    q, centres, forward, spread = _focus(c2w)
    if spread <= MIN_SPREAD or _inward(q, centres, forward) < _MIN_INWARD:
        return None
    return float((centres - q).norm(dim=-1).median())


def bounded_capture(scene: Scene, contraction: str | None) -> bool:
    """Whether ``scene`` trained with ``contraction`` is a capture (not a NeRF-synthetic render)
    trained bounded, which the near distance and the distortion loss treat apart."""
    return scene.source != "nerf-synthetic" and contraction is None


def capture_near(scene: Scene, contraction: str | None) -> float:
    """The rays' near distance for ``scene`` trained with ``contraction`` (see the module
    docstring): for a bounded capture of pinhole cameras that look at one point, the larger of the
    scene's own near and :data:`FOCUS_NEAR_SHARE` of the cameras' median distance to it; else the
    scene's (a fisheye's wide view may hold content closer to its camera)."""
    if not bounded_capture(scene, contraction) or scene.train.fisheye:
        return scene.near
    focus = focus_distance(scene.train.c2w)
    return scene.near if focus is None else max(scene.near, round(FOCUS_NEAR_SHARE * focus, 6))


def choose_contraction(setting: str | None, scene: Scene) -> str | None:
    """The contraction to train with: ``setting`` itself (``"l2"``, ``"linf"`` or None), or with
    ``"auto"`` the scene's own (see the module docstring)."""
    if setting != "auto":
        if setting is not None and setting not in CONTRACTIONS:
            raise ValueError(f"contraction must be 'auto', None or one of {', '.join(CONTRACTIONS)}, got {setting!r}")
        return setting
    if scene.contraction is not None:
        return scene.contraction
    if scene.source != "nerf-synthetic" and cameras_surround_centre(scene.train.c2w):
        return None if plain_backdrop(scene.train.images, scene.train.masks) else "l2"
    return None


def choose_aabb_scale(setting: int | str | None, scene: Scene, contraction: str | None) -> int | None:
    """The field's box to train with, as instant-ngp's ``aabb_scale`` about the finest cascade's
    box: ``setting`` itself (a power of two, or None for the box the scene's files give), or with
    ``"auto"`` :func:`seen_aabb_scale` for a COLMAP capture that trains bounded around a plain
    backdrop, else None. Such a capture has no sparse points beyond its subject, so the box
    :func:`~ngp_warp.data.scene_normalisation.normalise_scene` picks holds the cameras (aabb_scale 4),
    while the subject fills only what every camera sees."""
    if setting != "auto":
        return setting
    object_on_backdrop = (scene.source == "colmap" and contraction is None
                          and cameras_surround_centre(scene.train.c2w)
                          and plain_backdrop(scene.train.images, scene.train.masks))
    return seen_aabb_scale(scene) if object_on_backdrop else None


def seen_aabb_scale(scene: Scene) -> int:
    """The smallest power of two k for which the box k times the finest cascade's box (about its
    centre) is as wide as the median training camera sees at that centre (its distance to it
    times the tangent of half its narrower field of view, on either side), capped at the box
    the scene's files give."""
    box = scene.occupancy_aabb.double()
    centre, unit = (box[:3] + box[3:]) / 2, float((box[3:] - box[:3]).max())
    split = scene.train
    distance = (split.c2w[:, :, 3].double() - centre).norm(dim=-1)
    fx, fy = split.intrinsics[:, 0].double(), split.intrinsics[:, 1].double()
    files = round(float((scene.aabb[3:] - scene.aabb[:3]).max()) / unit)
    if split.fisheye:
        return files
    half_view = torch.minimum(split.width / (2 * fx), split.height / (2 * fy))  # tan(half field of view)
    seen = 2 * float((distance * half_view).median())
    return min(2 ** max(0, math.ceil(math.log2(max(seen / unit, 1.0)))), files)


def edge_pixels(images: torch.Tensor, masks: torch.Tensor | None = None) -> torch.Tensor:
    """[P, 3] the RGB of every pixel on the outer edges of ``images`` ([N, H, W, C], any dtype;
    corners counted twice), where a capture mostly sees what lies beyond its subject; with
    training ``masks`` ([N, H, W] bool) only the pixels they keep, unless they keep none there."""
    def edges(a: torch.Tensor) -> torch.Tensor:
        return torch.cat([a[:, 0], a[:, -1], a[:, :, 0], a[:, :, -1]], 1)
    rgb = edges(images)[..., :3].reshape(-1, 3)
    kept = None if masks is None else edges(masks).reshape(-1)
    return rgb if kept is None or not bool(kept.any()) else rgb[kept]


def plain_backdrop(images: torch.Tensor, masks: torch.Tensor | None = None) -> bool:
    """Whether ``images`` ([N, H, W, C] uint8) show their subject on one plain colour, as
    object captures composited on white (or masked onto any one colour) do: at least 98 % of the
    pixels on the images' outer edges lie within 8 levels of their median colour in every
    channel. Such a capture has nothing beyond its subject, so it trains bounded: contracted,
    the demo scene on white as a COLMAP model scored 20.6 dB at 60 s on an H100 against 28.9
    bounded, while over the unbounded scene's sky at infinity it scored 24.8 against 16.1.
    Pixels that training ``masks`` ([N, H, W] bool) leave out do not count."""
    border = edge_pixels(images, masks).to(torch.int16)
    median = border.median(0).values
    close = ((border - median).abs() <= _BACKDROP_TOLERANCE).all(-1)
    return float(close.float().mean()) >= _BACKDROP_SHARE


@torch.no_grad()
def start_environment(environment: torch.nn.Linear, images: torch.Tensor, masks: torch.Tensor | None) -> None:
    """Start the learned environment (:meth:`NGPField.background`) at the mean colour of the
    training images' outermost pixels, where a capture mostly sees its background. Adam moves
    the sigmoid's bias by about the learning rate per step, so from grey a white backdrop takes
    hundreds of steps, while density in front of the cameras learns to paint it in a few (the
    demo scene as a COLMAP model: 9.7 dB after 300 CPU steps from grey, 16.3 from here, as
    with the backdrop given); the pixels training ``masks`` leave out do not count."""
    colour = edge_pixels(images, masks).float().mean(0) / 255.0
    environment.bias.copy_(torch.logit(colour.clamp(0.02, 0.98)))


def with_backdrop_alpha(images: torch.Tensor) -> torch.Tensor:
    """[N, H, W, 4] uint8: opaque [N, H, W, 3] uint8 ``images`` with alpha 0 where every channel
    is 255 (the backdrop), 255 elsewhere."""
    backdrop = (images == 255).all(-1, keepdim=True)
    return torch.cat([images, torch.where(backdrop, 0, 255).to(torch.uint8)], -1)


def contraction_box(scene: Scene, fit: str = "cameras") -> torch.Tensor:
    """[6] float32 inner box of the contraction: the finest cascade's box, grown about its centre
    (keeping its proportions) until it holds every training camera (``fit`` "cameras"), or to the
    box the median camera sees at that centre (``fit`` "seen", :func:`seen_aabb_scale`; cameras
    farther out lie in contracted space)."""
    if fit not in CONTRACTION_FITS:
        raise ValueError(f"contraction_fit must be one of {', '.join(CONTRACTION_FITS)}, got {fit!r}")
    box = scene.occupancy_aabb.double()
    centre, half = (box[:3] + box[3:]) / 2, (box[3:] - box[:3]) / 2
    if fit == "seen":
        grow = float(seen_aabb_scale(scene))
    else:
        reach = ((scene.train.c2w[:, :, 3].double() - centre).abs() / half).amax()
        grow = max(1.0, float(reach) * 1.05)
    return torch.cat([centre - half * grow, centre + half * grow]).float()


def occupancy_threshold(scene: Scene) -> float:
    """The occupancy grid's threshold for ``scene`` (see the module docstring)."""
    return SYNTHETIC_OCCUPANCY_THRESHOLD if scene.source == "nerf-synthetic" else CAPTURE_OCCUPANCY_THRESHOLD


def distortion_weight(scene: Scene, contraction: str | None) -> float:
    """The distortion loss's weight for ``scene`` (see the module docstring)."""
    return CAPTURE_DISTORTION_WEIGHT if bounded_capture(scene, contraction) else 0.0


def capture_start(scene: Scene, contraction: str | None, device_type: str, samples_per_step: int,
                  subrays: int, budget_steps: int | None = None) -> tuple[int, int, bool]:
    """The learning rate's warm-up steps, the occupancy grid's open steps and whether its
    refreshes count only seen points, for ``scene`` trained with ``contraction`` on a device of
    ``device_type`` ("cuda" or "cpu") at ``samples_per_step`` trained samples a step (one
    rank's) and ``subrays`` rays a pixel (see the module docstring): every other run's start
    (100 steps, no open grid, every point's density) unless the steps that meet :data:`START_PIXEL_SHARE` of
    the training pixels, at :data:`NOMINAL_SAMPLES_PER_RAY`, are more than that; at most
    :data:`CAPTURE_WARMUP_STEPS`, and a tenth of ``budget_steps`` where the run counts steps
    (a time budget's steps are not known before it runs)."""
    if not bounded_capture(scene, contraction) or device_type != "cuda":
        return WARMUP_STEPS, 0, False
    images = scene.train.images
    pixels = images.shape[0] * images.shape[1] * images.shape[2]
    pixels_per_step = samples_per_step / (subrays * NOMINAL_SAMPLES_PER_RAY)
    longest = CAPTURE_WARMUP_STEPS if budget_steps is None else min(CAPTURE_WARMUP_STEPS, budget_steps // 10)
    steps = min(round(START_PIXEL_SHARE * pixels / pixels_per_step), longest)
    if steps <= WARMUP_STEPS:
        return WARMUP_STEPS, 0, False
    return steps, steps, True


def appearance_dim(scene: Scene) -> int:
    """Appearance code size for ``scene``: 0 for NeRF-synthetic, else APPEARANCE_DIM."""
    return 0 if scene.source == "nerf-synthetic" else APPEARANCE_DIM

