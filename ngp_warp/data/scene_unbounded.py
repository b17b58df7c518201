"""The project's unbounded 360° procedural scene (``kernels/scene_unbounded.py``), rendered exactly by
a Warp tracer and written as a NeRF-synthetic-style folder: ``transforms_{train,test}.json``,
``train/r_i.png`` and ``test/r_i.png`` (opaque RGB: the background is part of the scene) and
``scene.json`` describing how it was made.

The transforms files carry two scene keys beside ``camera_angle_x``: ``"contraction": "l2"``
(the scene is unbounded: contract beyond the inner box, see :mod:`ngp_warp.ops.contraction`) and
``"aabb"``, the inner box [[-4, -4, -4], [4, 4, 4]], which holds every camera and the objects.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from ngp_warp import _wp
from ngp_warp.kernels import scene as objects
from ngp_warp.kernels import scene_unbounded as K
from ngp_warp.data.scene import look_at
from ngp_warp.data.scene_folder import check_positive_ints, check_views, write_rendered_scene

CAMERA_ANGLE_X = 0.9  # horizontal field of view, radians
RING_RADIUS = 3.6  # cameras circle the centre at this distance (jittered by 5 % in training)
TRAIN_HEIGHTS = (0.6, 1.2, 2.0)  # above the ground: train view i is on ring i % 3
TEST_HEIGHTS = (0.9, 1.6)  # test views alternate between these, between the train rings
LOOK_AT = (0.0, 0.0, 0.0)  # every camera looks at the objects' centre
INNER_HALF = 4.0  # the inner (uncontracted) box is [-INNER_HALF, INNER_HALF]^3
CONTRACTION = "l2"


def render_unbounded_views(c2w: torch.Tensor, intrinsics: torch.Tensor, width: int, height: int,
                           supersample: int = 3) -> torch.Tensor:
    """Render the unbounded scene from cameras, on their device.

    Args:
        c2w: [V, 3, 4] float32 camera-to-world, OpenGL convention.
        intrinsics: [V, 4] float32 fx, fy, cx, cy in pixels.
        width, height: image size in pixels.
        supersample: ss; each pixel averages ss x ss stratified rays (a box filter).

    Returns:
        [V, H, W, 3] float32 RGB in [0, 1]: the mean colour of the pixel's ss² rays (every ray
        has a colour: the environment closes the scene).
    """
    check_views(c2w, intrinsics, width, height, supersample)
    n_views = c2w.shape[0]
    out = torch.empty(n_views * height * width, 3, dtype=torch.float32, device=c2w.device)
    _wp.launch(K.render_views, out.shape[0],
               [_wp.to_wp(c2w.contiguous()), _wp.to_wp(intrinsics.contiguous()), width, height,
                supersample, out], _wp.device_of(c2w))
    return out.reshape(n_views, height, width, 3)


def render_unbounded_rays(rays_o: torch.Tensor, rays_d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact colour and depth of single rays (ground truth for tests and benchmarks).

    Args:
        rays_o: [N, 3] float32 origins (above the ground, outside the pillars).
        rays_d: [N, 3] float32 non-zero directions (normalised inside), same device.

    Returns:
        ``(rgb [N, 3], depth [N])`` float32: the colour, and the distance along the unit direction
        to the first surface, -1 (``kernels.scene_unbounded.MISS``) for rays reaching the environment.
    """
    for name, t in (("rays_o", rays_o), ("rays_d", rays_d)):
        if not isinstance(t, torch.Tensor) or t.dim() != 2 or t.shape[1] != 3 or t.dtype != torch.float32:
            raise ValueError(f"{name} must be a [N, 3] float32 tensor, got {getattr(t, 'shape', type(t).__name__)}")
    if rays_d.shape != rays_o.shape or rays_d.device != rays_o.device:
        raise ValueError("rays_o and rays_d must have the same shape and device")
    n = rays_o.shape[0]
    rgb = torch.empty(n, 3, dtype=torch.float32, device=rays_o.device)
    depth = torch.empty(n, dtype=torch.float32, device=rays_o.device)
    _wp.launch(K.render_rays, n, [rays_o.contiguous(), rays_d.contiguous(), rgb, depth], _wp.device_of(rays_o))
    return rgb, depth


def environment_colours(rays_d: torch.Tensor) -> torch.Tensor:
    """The scene's environment at infinity alone (mountains under a skyline, sky above), as a
    background for other scenes.

    Args:
        rays_d: [N, 3] float32 non-zero world directions (normalised inside), z up.

    Returns:
        [N, 3] float32 RGB in [0, 1], on the directions' device.
    """
    if not isinstance(rays_d, torch.Tensor) or rays_d.dim() != 2 or rays_d.shape[1] != 3 or rays_d.dtype != torch.float32:
        raise ValueError(f"rays_d must be a [N, 3] float32 tensor, got {getattr(rays_d, 'shape', type(rays_d).__name__)}")
    rgb = torch.empty_like(rays_d)
    _wp.launch(K.environment_rays, rays_d.shape[0], [rays_d.contiguous(), rgb], _wp.device_of(rays_d))
    return rgb


def _ring(azimuth: np.ndarray, radius: np.ndarray, height: np.ndarray) -> np.ndarray:
    """[n, 3, 4] float64 cameras at (r cos a, r sin a, GROUND_Z + height) looking at LOOK_AT."""
    pos = np.stack([radius * np.cos(azimuth), radius * np.sin(azimuth), K.GROUND_Z + height], -1)
    return np.stack([look_at(p, LOOK_AT) for p in pos])


def unbounded_cameras(n_train: int, n_test: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Camera-to-world matrices ([n, 3, 4] float64) of the train and test views, all looking inward.

    Train view i: ring ``TRAIN_HEIGHTS[i % 3]``, golden-angle azimuths turned by ``seed``, with
    azimuth and radius jitter. Test views: one even turn alternating between the
    ``TEST_HEIGHTS``, which lie between the train rings, so no test view is a train view.
    """
    rng = np.random.default_rng(seed)
    k = np.arange(n_train)
    azimuth = k * math.pi * (3.0 - math.sqrt(5.0)) + rng.uniform(0, 2 * math.pi) + rng.normal(0, 0.05, n_train)
    radius = RING_RADIUS * (1.0 + rng.uniform(-0.05, 0.05, n_train))
    train = _ring(azimuth, radius, np.asarray(TRAIN_HEIGHTS)[k % len(TRAIN_HEIGHTS)])
    k = np.arange(n_test)
    azimuth = 2 * math.pi * (k + 0.5) / n_test + rng.uniform(0, 2 * math.pi)
    test = _ring(azimuth, np.full(n_test, RING_RADIUS), np.asarray(TEST_HEIGHTS)[k % len(TEST_HEIGHTS)])
    return train, test


def scene_keys() -> dict:
    """The scene keys written beside ``camera_angle_x`` in both transforms files."""
    h = INNER_HALF
    return {"contraction": CONTRACTION, "aabb": [[-h, -h, -h], [h, h, h]]}


def _description(width, height, n_train, n_test, seed, supersample) -> dict:
    return {
        "generator": "ngp-warp unbounded scene",
        "width": width, "height": height, "n_train": n_train, "n_test": n_test, "seed": seed,
        "supersample": supersample, "camera_angle_x": CAMERA_ANGLE_X, "ring_radius": RING_RADIUS,
        "train_heights": TRAIN_HEIGHTS, "test_heights": TEST_HEIGHTS, "look_at": LOOK_AT,
        "objects": "the demo scene's four (see ngp_warp.data.scene), unchanged",
        "ground": {"z": K.GROUND_Z, "checker_cell": K.GROUND_CELL, "colours": [K.GROUND_A, K.GROUND_B],
                   "contrast_fade": K.GROUND_FADE},
        "pillars": {"count": K.PILLAR_COUNT, "ring": K.PILLAR_RING, "radius": K.PILLAR_RADIUS,
                    "height": K.PILLAR_HEIGHT, "phase": K.PILLAR_PHASE},
        "environment": {"skyline_base": K.SKYLINE_BASE, "skyline_waves": K.SKYLINE_WAVES,
                        "sky": [K.SKY_HORIZON, K.SKY_ZENITH], "mountains": [K.MOUNTAIN_LOW, K.MOUNTAIN_HIGH]},
        "light": {"direction": objects.LIGHT_DIR, "ambient": objects.AMBIENT, "diffuse": objects.DIFFUSE},
        **scene_keys(),
    }


def write_unbounded_scene(out_dir: str | Path, *, width: int = 100, height: int = 100, n_train: int = 60,
                          n_test: int = 10, seed: int = 0, supersample: int = 3, overwrite: bool = False) -> Path:
    """Render the unbounded scene and write it as a scene folder at ``out_dir`` (see the module doc).

    Written into a temporary sibling folder renamed into place at the end, so a failure leaves
    nothing behind (not even parent folders this call created).

    Args:
        out_dir: folder to create; it must not exist unless ``overwrite``.
        width, height: image size in pixels.
        n_train, n_test: number of train and test views.
        seed: turns and jitters the cameras; the same seed gives the same files.
        supersample: each pixel averages ``supersample**2`` rays (anti-aliasing).
        overwrite: replace an existing ``out_dir``.

    Returns:
        The folder written, as a Path.

    Raises:
        DataError: ``out_dir`` exists (without ``overwrite``) or cannot be written.
    """
    check_positive_ints(width=width, height=height, n_train=n_train, n_test=n_test, supersample=supersample)

    def render(c2w: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
        return render_unbounded_views(c2w, intrinsics, width, height, supersample)

    return write_rendered_scene(out_dir, overwrite, "the unbounded scene", unbounded_cameras(n_train, n_test, seed),
                                width, height, CAMERA_ANGLE_X, render, scene_keys(),
                                _description(width, height, n_train, n_test, seed, supersample))
