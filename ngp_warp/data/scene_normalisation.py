"""Fit a captured scene (cameras + sparse points, any frame and scale) into instant-ngp's box.

The scene frame: up is +z, the cameras' focus at the origin, the cameras on average
:data:`CAMERA_RADIUS` away (instant-ngp's colmap2nerf does the same); instant-ngp then maps it
to its unit cube by p * 0.33 + 0.5 (``ngp_warp.data.transforms_json``).
"""

from __future__ import annotations

import math

import numpy as np

from ngp_warp.data.transforms_json import NGP_SCALE  # instant-ngp's world -> unit-cube scale

CAMERA_RADIUS = 4.0  # mean camera distance from the centre, scene units ("NeRF sized")
POINT_QUANTILE = 0.99  # the field's box holds this share of the sparse points (far outliers left out)
MAX_AABB_SCALE = 128  # instant-ngp's largest
MIN_SPREAD = 0.01  # smallest eigenvalue of mean(I - f f^T) for the cameras' focus to be trusted (~6 degrees)


def _rotation_onto_z(up: np.ndarray) -> np.ndarray:
    """[3, 3] rotation taking the unit vector ``up`` onto +z (Rodrigues, about up x z)."""
    z = np.array([0.0, 0.0, 1.0])
    axis, cos = np.cross(up, z), float(up @ z)
    if np.linalg.norm(axis) < 1e-12:
        return np.eye(3) if cos > 0 else np.diag([1.0, -1.0, -1.0])
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + k + k @ k / (1 + cos)


def axes_focus(origins: np.ndarray, forward: np.ndarray) -> tuple[np.ndarray, float]:
    """The point [3] nearest every camera's optical axis (least squares; ``origins`` [N, 3] and
    unit ``forward`` [N, 3] float64), and the smallest eigenvalue of mean(I − f fᵀ): how far the
    axes spread, near 0 where they are parallel and the point is unsettled (trusted above
    :data:`MIN_SPREAD`)."""
    proj = np.eye(3) - forward[:, :, None] * forward[:, None, :]  # [N, 3, 3] I - f f^T
    a, b = proj.mean(0), np.einsum("nij,nj->i", proj, origins) / len(origins)
    return np.linalg.lstsq(a, b, rcond=None)[0], float(np.linalg.eigvalsh(a)[0])


def _centre(origins: np.ndarray, forward: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The point nearest every camera's optical axis (least squares) when the axes converge in
    front of the cameras; else the median sparse point; else the mean camera centre."""
    focus, spread = axes_focus(origins, forward)
    if spread > MIN_SPREAD and np.median(np.einsum("ni,ni->n", focus - origins, forward)) > 0:
        return focus
    return np.median(points, axis=0) if len(points) else origins.mean(0)


def normalise_scene(c2w: np.ndarray, points: np.ndarray,
                    aabb_scale: int | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """The similarity that puts a capture in the scene frame, and the box the field needs there.

    * up: the mean of the cameras' up vectors (OpenGL +y), rotated onto +z;
    * centre: where the cameras look (the point nearest all optical axes) when they converge,
      else the median sparse point;
    * scale: the cameras' mean distance from the centre becomes :data:`CAMERA_RADIUS`;
    * aabb_scale: the smallest power of two (at most :data:`MAX_AABB_SCALE`) whose instant-ngp
      box [0.5 -+ aabb_scale / 2]^3 holds every camera and :data:`POINT_QUANTILE` of the points.

    Args:
        c2w: [N, 4, 4] float64 camera-to-world, OpenGL convention, in the capture's frame.
        points: [P, 3] float64 sparse points in that frame (P may be 0).
        aabb_scale: use this box instead of picking one.

    Returns:
        scene_from_world, world_from_scene: [4, 4] float64 similarities (s R, -s R c; 0, 1) and
        their inverse; aabb_scale: int.
    """
    up = c2w[:, :3, 1].mean(0)
    up = up / np.linalg.norm(up) if np.linalg.norm(up) > 1e-9 else np.array([0.0, 0.0, 1.0])
    rotation = _rotation_onto_z(up)
    origins, forward = c2w[:, :3, 3], -c2w[:, :3, 2]
    centre = _centre(origins, forward, points)
    radius = float(np.linalg.norm(origins - centre, axis=1).mean())
    if radius < 1e-9 and len(points):  # cameras at one spot: scale by the points instead
        radius = float(np.median(np.linalg.norm(points - centre, axis=1)))
    scale = CAMERA_RADIUS / max(radius, 1e-9)
    scene_from_world = np.eye(4)
    scene_from_world[:3, :3] = scale * rotation
    scene_from_world[:3, 3] = -scale * rotation @ centre
    world_from_scene = np.eye(4)
    world_from_scene[:3, :3] = rotation.T / scale
    world_from_scene[:3, 3] = centre
    if aabb_scale is None:
        def in_scene(p: np.ndarray) -> np.ndarray:  # [M, 3] -> max-norm of each point in the scene frame
            return np.abs(scale * (p - centre) @ rotation.T).max(1)

        extent = float(in_scene(origins).max())
        if len(points):
            extent = max(extent, float(np.quantile(in_scene(points), POINT_QUANTILE)))
        aabb_scale = 2 ** max(0, math.ceil(math.log2(max(2 * NGP_SCALE * extent, 1.0))))
        aabb_scale = min(aabb_scale, MAX_AABB_SCALE)
    return scene_from_world, world_from_scene, int(aabb_scale)
