"""Training settings: :class:`TrainConfig`, its ``key=value`` overrides and the defaults resolved
per device and per scene (the command line itself is parsed by :mod:`ngp_warp.cli`)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

from ngp_warp._checks import check_numbers
from ngp_warp.data.loading import Scene
from ngp_warp.ops.field import INSTANT_NGP_FINEST_RESOLUTION, MAX_RESOLUTION, FieldConfig
from ngp_warp.training.memory_estimate import MAX_SAMPLES_PER_CALL
from ngp_warp.training.model import FAR
from ngp_warp.training.scene_defaults import (AUTO_FIT, CONTRACTION_FITS, PROBE_FIT, appearance_dim, capture_near,
                                             capture_start, choose_aabb_scale, choose_contraction, cone_steps, contraction_box,
                                             distortion_weight, occupancy_threshold)
from ngp_warp.data.transforms_json import CONTRACTIONS, MAX_AABB_SCALE

AABB_SCALES = tuple(2**k for k in range(MAX_AABB_SCALE.bit_length()))  # field boxes of 1 ... 2^15 unit cubes
MIN_GRID_RESOLUTION = 4  # occupancy cells a side (16-px demo, 150 steps: 8.9, 10.5, 13.7, 15.4 dB at 1, 2, 4, 16)


@dataclass
class TrainConfig:
    """Training settings; ``None`` sizes pick a default for the device."""

    steps: int | None = None            # stop after this many steps ...
    seconds: float | None = None        # ... or after this much training wall-clock
    target_samples: int | None = None   # samples per batch to hold (2^18 CUDA, 2^15 CPU); with
                                        # prune, samples that composite (the rows trained on)
    initial_rays: int = 1024
    max_rays: int = 1 << 18
    lr: float = 1e-2
    lr_warmup: int | None = None        # steps of the learning rate's linear warm-up; None: 100, or a
                                        # bounded capture's start on CUDA (scene_defaults.capture_start)
    weight_decay: float = 1e-6          # on MLP weights only
    loss: str = "l2"                    # "l2" or "huber"
    seed: int = 0
    grid_resolution: int = 128
    steps_per_diagonal: int = 1024      # marching step = finest cascade's diagonal / this
    cone_angle: float | None = None     # Δt = clamp(t·cone_angle, step, max); None: per scene (1/256 for
                                        # scenes beyond the unit box or unbounded, 0 for NeRF-synthetic)
    contraction: str | None = "auto"    # "l2" | "linf" | None: unbounded space contracted (mip-NeRF 360,
                                        # nerfstudio's L∞); "auto": the scene's (scene_defaults)
    contraction_fit: str = "auto"       # with a contraction, its inner box holds every camera ("cameras")
                                        # or what the median camera sees at the centre ("seen"); "probe":
                                        # bounded or "cameras", by a short training (training.contraction_probe);
                                        # "auto": the probe where the scene's rule contracts and the run can
                                        # train one (train on one rank, fit-many), else "cameras"
    aabb_scale: int | str | None = "auto"  # the field's box, instant-ngp's aabb_scale (a power of two);
                                        # None: the scene files'; "auto": per scene (scene_defaults)
    early_stop_eps: float = 1e-4
    occupancy_threshold: float | None = None  # a grid cell is occupied while its optical thickness over
                                        # one step, σ·step, exceeds min(this, the mean); None: per scene
                                        # (instant-ngp's 0.01 on NeRF-synthetic, 0.05 on captures)
    occupancy_decay: float = 0.95       # each grid refresh (every 16 steps) scales old estimates by this
    occupancy_open_steps: int | None = None  # the first steps count every cell occupied whose estimate
                                        # is above 0 (every visible one; with grid_seen_only, those a
                                        # training ray can sample); the estimates still refresh; None: 0,
                                        # or a bounded capture's start on CUDA
    grid_seen_only: bool | None = None  # a refresh counts density only at points that a training ray
                                        # can sample (some training image holds them, past the near);
                                        # pinhole and OpenCV lenses (fisheye: ignored); it tests
                                        # the starting poses (camera_refinement moves them); None:
                                        # on, for the whole run, where a bounded capture on CUDA
                                        # starts slowly (scene_defaults.capture_start)
    mlp_precision: str = "bf16"         # CUDA only (the CPU runs fp32): "bf16" autocast inside the
                                        # field's graphs, "tf32" matmuls, or "fp32"
    prune: bool = True                  # train only on samples that composite (no-grad σ pass first)
    cuda_graph: bool = True             # CUDA with prune: replay the field's forward/backward as graphs
    weight_average: float = 0.995       # > 0: render with an EMA of the weights, this decay per step
    lazy_table_adam: bool = True        # Adam skips hash-table entries with zero gradient (tiny-cuda-nn),
                                        # and keeps their weight average in the same pass
    supersample: int | None = None      # > 1: each training pixel is the mean of supersample² rays on
                                        # a sub-pixel grid (as the images were area-downsampled), and
                                        # renders average the same grid; None: 2 on CUDA, 1 on the CPU
    distortion_weight: float | None = None  # weight of the mean distortion loss per ray (distances as
                                        # below); None: per scene (4e-3 on bounded captures, else 0)
    distortion_spacing: str = "normalised"  # the loss's distances: mip-NeRF 360's s = 1 − near/t
                                        # (near the camera counts more), or "world" (t)
    near_gradient_distance: float = 0.0  # > 0: σ and colour gradients scaled by min(1, (t / this)²),
                                        # t from the camera in world units (Floaters No More)
    backdrop_alpha: bool = False        # train opaque images of an object on white as if the white were
                                        # transparent (alpha 0 where every channel is 255), over random
                                        # backgrounds (an experiment: see docs/captures.md)
    near: float | None = None           # rays start this far from their camera, in the scene's lengths;
                                        # None: per scene (a bounded capture: 0.3 of its cameras' median
                                        # distance to where they look, or the scene's own near if larger;
                                        # else the scene's, instant-ngp's 0.1 of its unit cube)
    camera_refinement: bool = False     # learn a pose correction per training image (bounded scenes)
    camera_lr: float = 1e-4             # its Adam learning rate (fox: instant-ngp's 1e-3 drifted 0.4°)
    field: FieldConfig = field(default_factory=FieldConfig)

    def check(self) -> None:
        """Raise ValueError naming the first setting outside its range (None is left to the
        device), the field's sizes included."""
        choices = {"loss": ("l2", "huber"), "mlp_precision": ("fp32", "tf32", "bf16"), "supersample": (None, 1, 2, 3, 4),
                   "contraction": ("auto", None, *CONTRACTIONS), "contraction_fit": (AUTO_FIT, *CONTRACTION_FITS, PROBE_FIT),
                   "distortion_spacing": ("world", "normalised")}
        for name, allowed in choices.items():
            value = getattr(self, name)
            if value not in allowed or type(value) not in (str, int, type(None)):
                shown = ", ".join("none" if a is None else str(a) for a in allowed)  # as --set takes them
                raise ValueError(f"{name} must be one of {shown}, got {value!r}")
        check_numbers(self, counts=("steps", "target_samples", "initial_rays", "max_rays", "grid_resolution",
                                     "lr_warmup", "steps_per_diagonal"),
                       positive=("seconds", "lr", "occupancy_threshold", "camera_lr", "near"),
                       non_negative=("weight_decay", "cone_angle", "early_stop_eps", "distortion_weight",
                                     "near_gradient_distance"),
                       optional=("steps", "seconds", "target_samples", "cone_angle", "occupancy_threshold",
                                 "distortion_weight", "near", "lr_warmup"))
        open_steps = self.occupancy_open_steps
        if open_steps is not None and (type(open_steps) is not int or open_steps < 0):
            raise ValueError(f"occupancy_open_steps must be an integer ≥ 0, got {open_steps!r}")
        if self.contraction_fit == PROBE_FIT and self.contraction != "auto":
            raise ValueError(f"contraction_fit 'probe' decides whether to contract: leave contraction at auto "
                             f"(got {self.contraction!r}), or give contraction_fit cameras or seen")
        if self.near is not None and self.near >= FAR:
            raise ValueError(f"near must be below the rays' far distance {FAR:g}, got {self.near!r}")
        if self.grid_resolution < MIN_GRID_RESOLUTION:
            raise ValueError(f"grid_resolution must be at least {MIN_GRID_RESOLUTION}: a grid of "
                             f"{self.grid_resolution}³ cells cannot tell empty space from the subject")
        if self.steps is not None and self.steps >= 2**63:
            raise ValueError(f"steps must be below 2^63, got {self.steps}")
        if self.target_samples is not None and self.target_samples > MAX_SAMPLES_PER_CALL:
            raise ValueError(f"target_samples must be at most {MAX_SAMPLES_PER_CALL} (the samples one kernel call "
                             f"takes), got {self.target_samples}")
        if self.aabb_scale not in ("auto", None, *AABB_SCALES) or type(self.aabb_scale) not in (str, int, type(None)):
            raise ValueError(f"aabb_scale must be auto, none or a power of two up to {AABB_SCALES[-1]}, "
                             f"got {self.aabb_scale!r}")
        if not 0.0 <= self.occupancy_decay < 1.0:
            raise ValueError(f"occupancy_decay must be in [0, 1), got {self.occupancy_decay!r}")
        if not 0.0 <= self.weight_average < 1.0:
            raise ValueError(f"weight_average must be in [0, 1), got {self.weight_average!r}")
        if type(self.backdrop_alpha) is not bool:
            raise ValueError(f"backdrop_alpha must be true or false, got {self.backdrop_alpha!r}")
        if self.grid_seen_only is not None and type(self.grid_seen_only) is not bool:
            raise ValueError(f"grid_seen_only must be true or false, got {self.grid_seen_only!r}")
        if type(self.camera_refinement) is not bool:
            raise ValueError(f"camera_refinement must be true or false, got {self.camera_refinement!r}")
        if type(self.seed) is not int or not 0 <= self.seed < 2**63:
            raise ValueError(f"seed must be an integer in [0, 2^63), got {self.seed!r}")
        self.field.check()
        _check_finite(self)

    def budget(self) -> tuple[int | None, float | None]:
        """(steps, seconds) to train for: 20000 steps when neither is set."""
        if self.steps is None and self.seconds is None:
            return 20000, None
        return self.steps, self.seconds


def _check_finite(config: TrainConfig) -> None:
    """ValueError naming the first float setting (the field's included) that is NaN or infinite."""
    for target, prefix in ((config, ""), (config.field, "field.")):
        for f in dataclasses.fields(target):
            value = getattr(target, f.name)
            if isinstance(value, float) and not math.isfinite(value):
                raise ValueError(f"{prefix}{f.name} must be finite, got {value!r}")


def apply_overrides(config: TrainConfig, settings: list[str]) -> TrainConfig:
    """A copy of ``config`` with ``key=value`` settings applied (``field.key`` for the field's
    sizes); values take the setting's declared type (``none`` for settings that may be None,
    e.g. ``field.finest_resolution`` or ``contraction``). Raises ValueError on unknown keys or values that do
    not parse."""
    config = dataclasses.replace(config, field=dataclasses.replace(config.field))
    for item in settings:
        key, sep, text = item.partition("=")
        target, name = (config.field, key[6:]) if key.startswith("field.") else (config, key)
        names = {f.name for f in dataclasses.fields(target)} - {"field"}
        if not sep and name in names:
            raise ValueError(f"{key} has no value; write {key}=VALUE")
        if not sep or name not in names:
            field_names = {"field." + f.name for f in dataclasses.fields(FieldConfig)}
            raise ValueError(f"unknown setting {item!r}; expected key=value with key one of "
                             f"{', '.join(sorted(names | field_names))}")
        declared = {f.name: f for f in dataclasses.fields(target)}[name]
        optional = declared.default is None or "None" in declared.type
        value = None if optional and text.lower() == "none" else _parse_value(declared.type, text, key)
        setattr(target, name, value)
    return config


def _parse_value(declared: str, text: str, key: str):
    """``text`` as the dataclass field's declared type (an annotation string such as
    ``"float | None"``: this module postpones annotations)."""
    kind = declared.split("|")[0].strip()
    if kind == "bool":
        if text.lower() not in ("true", "false", "1", "0"):
            raise ValueError(f"{key} takes true or false, got {text!r}")
        return text.lower() in ("true", "1")
    if kind == "str" or ("str" in declared and not text.lstrip("+-").isdigit()):  # int | str: a word stays text
        return text
    try:
        return int(text) if kind == "int" else float(text)
    except ValueError:
        raise ValueError(f"{key} takes {'an integer' if kind == 'int' else 'a number'}, got {text!r}") from None


def default_device() -> str:
    """``cuda`` when torch and Warp both see a GPU, else ``cpu``."""
    from ngp_warp import _wp

    return "cuda" if _wp.cuda_available() else "cpu"


CPU_GRID_RESOLUTION = 64      # ngp-warp's sizes on the CPU (the command line's and the demo's):
CPU_LOG2_HASHMAP_SIZE = 16    # 2 cores train lego 2x the steps (26.8 vs 24.1 dB at 150 s, RESULTS.md)


def cpu_sizes(config: TrainConfig) -> TrainConfig:
    """``config`` with the CPU's smaller occupancy grid and hash table
    (:data:`CPU_GRID_RESOLUTION`, :data:`CPU_LOG2_HASHMAP_SIZE`), in place and returned. On 2
    cores the GPU-sized field spends a step in its 64 MB table: lego_half at 150 s reached 24.1
    dB in 710 steps, against 26.8 dB in 1424 with these; fox at downscale 8, 19.4 against 26.9."""
    config.grid_resolution = CPU_GRID_RESOLUTION
    config.field.log2_hashmap_size = CPU_LOG2_HASHMAP_SIZE
    return config


def device_defaults(config: TrainConfig, device_type: str) -> TrainConfig:
    """``config`` with ``supersample`` filled in when left to None: 2×2 sub-rays per training
    pixel on CUDA, one ray on the CPU.

    On lego (H200, schedule over 300 s, 200 views, RESULTS.md) the sub-rays took the 300 s PSNR
    from 34.75 to 36.61 dB. With them, a 2^21-entry table and a distortion loss no longer
    helped (36.67–36.74 dB at 300 s with or without them, 25 views; benchmarks/NOTES.md), so the table
    is instant-ngp's 2^19 and the distortion loss is off by default on both devices. On the CPU,
    2×2 sub-rays gave 33.18 against 33.56 dB on the demo in 150 s on 2 cores.
    """
    if config.supersample is not None:
        return config
    return dataclasses.replace(config, supersample=2 if device_type == "cuda" else 1)


def default_target_samples(config: TrainConfig, device_type: str) -> int:
    """The samples per batch to hold: the config's, else 2^18 on CUDA and 2^15 on the CPU. Left
    out of the resolved config, so a resumed run takes its new device's default."""
    return config.target_samples or (1 << 18 if device_type == "cuda" else 1 << 15)


def pixel_matched_resolution(scene: Scene, subpixels: int = 1, contraction: str | None = None,
                             contraction_fit: str = "cameras") -> float:
    """The finest hash-grid resolution whose cells are about one training pixel wide at the
    field box's centre: the box's longest side over the median pixel footprint (camera distance
    to the centre over the focal length fx), rounded, clamped to [64, 2048 per unit cube]
    (instant-ngp's 2048 × aabb_scale) and to 2^24. Training on ``subpixels``² rays per pixel
    makes the cells √subpixels times finer.

    On lego at 400×400 this gives 413 cells. Measured there after 60 s (RESULTS.md): finest
    256 / 362 / 512 / 724 / 1024 / 2048 give 34.97 / 35.31 / 35.25 / 35.03 / 34.74 / 34.43 dB:
    levels finer than the pixels let the field fit each training ray on its own, which the test
    views do not share. With 2×2 sub-rays per pixel (H200, 300 s, 25 views) finest 413 / 584 /
    826 gave 36.67 / 36.84 / 36.70 dB, and with 3×3, 716 against 1239 cells gave 36.95 against
    36.76 dB: the sub-rays resolve detail finer than a pixel, but not a full sub-pixel's worth.

    With a ``contraction`` the box is the contraction's inner box
    (:func:`ngp_warp.training.scene_defaults.contraction_box`), which fills half of the hash grid's side
    (its [-1, 1] in the contracted [-2, 2]): the resolution returned is twice the box's.
    """
    split = scene.train
    box = (scene.aabb if contraction is None else contraction_box(scene, contraction_fit)).double()
    centre = 0.5 * (box[:3] + box[3:])
    distance = (split.c2w[:, :, 3].double() - centre).norm(dim=-1)
    footprint = float((distance / split.intrinsics[:, 0].double()).median()) / math.sqrt(subpixels)
    side = float((box[3:] - box[:3]).max())
    unit = float((scene.occupancy_aabb[3:] - scene.occupancy_aabb[:3]).max())
    ceiling = INSTANT_NGP_FINEST_RESOLUTION * side / unit
    grid_sides = 1 if contraction is None else 2
    return float(min(grid_sides * min(max(round(side / max(footprint, 1e-12)), 64), ceiling), MAX_RESOLUTION))


def resolve_defaults(config: TrainConfig, scene: Scene, device_type: str) -> TrainConfig:
    """``config``, checked, or a copy with the settings left to None or "auto" filled in for the
    device (:func:`device_defaults`) and the scene (:mod:`ngp_warp.training.scene_defaults`: the
    contraction, the field's box, the cone angle, the occupancy threshold, the distortion weight,
    the near distance, the start (warm-up, open grid, seen-only refreshes) and the appearance
    code size; the finest resolution, by
    :func:`pixel_matched_resolution`), so that checkpoints store the values used. Raises
    ValueError naming a setting out of range."""
    config.check()
    config = device_defaults(config, device_type)
    kind = choose_contraction(config.contraction, scene)
    if kind is not None and config.contraction_fit == PROBE_FIT:
        raise ValueError("contraction_fit 'probe' is decided by a short training, which ngp-warp train, demo "
                         "and fit-many run (ngp_warp.training.contraction_probe.probed_trainer); here use "
                         "'auto', 'cameras' or 'seen'")
    if config.contraction_fit == AUTO_FIT:  # no probe here: the box holding the cameras
        config = dataclasses.replace(config, contraction_fit="cameras")
    aabb_scale = choose_aabb_scale(config.aabb_scale, scene, kind)
    scene = scene.with_aabb_scale(aabb_scale)
    cone = cone_steps(scene, kind)[0] if config.cone_angle is None else config.cone_angle
    threshold = config.occupancy_threshold
    threshold = occupancy_threshold(scene) if threshold is None else threshold
    distortion = distortion_weight(scene, kind) if config.distortion_weight is None else config.distortion_weight
    near = capture_near(scene, kind) if config.near is None else config.near
    warmup, open_steps, seen_only = capture_start(scene, kind, device_type, default_target_samples(config, device_type),
                                                  config.supersample ** 2, config.budget()[0])
    config = dataclasses.replace(
        config, contraction=kind, aabb_scale=aabb_scale, cone_angle=cone, occupancy_threshold=threshold,
        distortion_weight=distortion, near=near, lr_warmup=warmup if config.lr_warmup is None else config.lr_warmup,
        occupancy_open_steps=open_steps if config.occupancy_open_steps is None else config.occupancy_open_steps,
        grid_seen_only=seen_only if config.grid_seen_only is None else config.grid_seen_only)
    field_config = config.field
    if field_config.appearance_dim is None:
        field_config = dataclasses.replace(field_config, appearance_dim=appearance_dim(scene))
    if field_config.environment is None:  # contracted fields learn the colour at infinity
        field_config = dataclasses.replace(field_config, environment=kind is not None)
    if field_config.finest_resolution is None:
        finest = pixel_matched_resolution(scene, config.supersample, kind, config.contraction_fit)
        field_config = dataclasses.replace(field_config, finest_resolution=finest)
    field_config.check()  # the finest resolution picked for the scene against the base one
    return dataclasses.replace(config, field=field_config)
