"""The project's own procedural scene, rendered exactly by a Warp sphere tracer and written as a
NeRF-synthetic folder (``transforms_{train,test}.json``, ``train/r_i.png``, ``test/r_i.png``,
RGBA on a transparent background, plus ``scene.json`` describing how it was made)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from ngp_warp import _wp
from ngp_warp.kernels import scene as K
from ngp_warp.data.scene_folder import check_positive_ints, check_views, write_rendered_scene

CAMERA_ANGLE_X = 0.6911112070083618  # the Blender scenes' horizontal field of view, radians
CAMERA_RADIUS = 4.0
TRAIN_ELEVATION = (8.0, 80.0)  # degrees; train views cover this band of the upper hemisphere
TEST_ELEVATION = (15.0, 55.0)  # test views: one spiral turn, a path of their own


def render_demo_views(c2w: torch.Tensor, intrinsics: torch.Tensor, width: int, height: int,
                      supersample: int = 3) -> torch.Tensor:
    """Render the demo scene from cameras, on their device.

    Args:
        c2w: [V, 3, 4] float32 camera-to-world, OpenGL convention.
        intrinsics: [V, 4] float32 fx, fy, cx, cy in pixels.
        width, height: image size in pixels.
        supersample: ss; each pixel averages ss x ss stratified rays.

    Returns:
        [V, H, W, 4] float32: straight (not premultiplied) RGB in [0, 1] and alpha = covered
        fraction of the pixel,

    .. math::
        \\alpha = \\frac{1}{ss^2} \\sum_s [\\text{ray } s \\text{ hits}],\\qquad
        \\mathrm{rgb} = \\frac{\\sum_{s\\,\\text{hits}} c(x_s, d_s)}{\\sum_s [\\text{ray } s \\text{ hits}]}.
    """
    check_views(c2w, intrinsics, width, height, supersample)
    device = _wp.device_of(c2w)
    n_views = c2w.shape[0]
    out = torch.empty(n_views * height * width, 4, dtype=torch.float32, device=c2w.device)
    _wp.launch(K.render_views, out.shape[0],
               [_wp.to_wp(c2w.contiguous()), _wp.to_wp(intrinsics.contiguous()), width, height,
                supersample, _wp.to_wp(out)], device)
    return out.reshape(n_views, height, width, 4)


def look_at(position: np.ndarray, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """[3, 4] float64 OpenGL camera-to-world at ``position`` looking at ``target`` (``up`` is up)."""
    forward = np.asarray(target, dtype=np.float64) - position
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, up)
    right = right / np.linalg.norm(right)
    cam_up = np.cross(right, forward)
    return np.stack([right, cam_up, -forward, position], axis=1)


def _on_sphere(azimuth: np.ndarray, elevation_deg: np.ndarray) -> np.ndarray:
    el = np.radians(elevation_deg)
    return CAMERA_RADIUS * np.stack([np.cos(el) * np.cos(azimuth), np.cos(el) * np.sin(azimuth), np.sin(el)], -1)


def demo_cameras(n_train: int, n_test: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Camera-to-world matrices ([n, 3, 4] float64) of the train and test views.

    Train views: a golden-angle spiral over the band ``TRAIN_ELEVATION`` of the sphere of radius
    ``CAMERA_RADIUS`` (even coverage), turned and jittered by ``seed``. Test views: one spiral
    turn over ``TEST_ELEVATION``, a different path, so no test view is a train view.
    """
    rng = np.random.default_rng(seed)
    k = np.arange(n_train) + 0.5
    lo, hi = np.sin(np.radians(TRAIN_ELEVATION))
    elevation = np.degrees(np.arcsin(lo + (hi - lo) * k / n_train))
    azimuth = k * math.pi * (3.0 - math.sqrt(5.0)) + rng.uniform(0, 2 * math.pi) + rng.normal(0, 0.05, n_train)
    train = np.stack([look_at(p) for p in _on_sphere(azimuth, elevation)])
    k = np.arange(n_test) + 0.5
    elevation = TEST_ELEVATION[0] + (TEST_ELEVATION[1] - TEST_ELEVATION[0]) * k / n_test
    azimuth = 2 * math.pi * k / n_test + rng.uniform(0, 2 * math.pi)
    test = np.stack([look_at(p) for p in _on_sphere(azimuth, elevation)])
    return train, test


def _scene_description(width, height, n_train, n_test, seed, supersample) -> dict:
    return {
        "generator": "ngp-warp demo scene",
        "width": width, "height": height, "n_train": n_train, "n_test": n_test, "seed": seed,
        "supersample": supersample, "camera_radius": CAMERA_RADIUS, "camera_angle_x": CAMERA_ANGLE_X,
        "objects": [
            {"shape": "sphere", "center": K.SPHERE_CENTER, "radius": K.SPHERE_RADIUS, "texture": "checker"},
            {"shape": "rounded box", "center": K.BOX_CENTER, "half_extents": K.BOX_HALF,
             "rounding": K.BOX_ROUND, "turn_z": K.BOX_ANGLE, "texture": "stripes"},
            {"shape": "torus", "center": K.TORUS_CENTER, "major": K.TORUS_MAJOR, "minor": K.TORUS_MINOR,
             "texture": "hue wheel"},
            {"shape": "rounded cylinder", "center": K.CYL_CENTER, "radius": K.CYL_RADIUS,
             "half_height": K.CYL_HALF_HEIGHT, "rounding": K.CYL_ROUND, "texture": "vertical gradient"},
        ],
        "light": {"direction": K.LIGHT_DIR, "ambient": K.AMBIENT, "diffuse": K.DIFFUSE,
                  "specular": K.SPECULAR, "shininess": K.SHININESS},
    }


def write_demo_scene(out_dir: str | Path, *, width: int = 100, height: int = 100, n_train: int = 50,
                     n_test: int = 10, seed: int = 0, supersample: int = 3, overwrite: bool = False,
                     device: str = "cpu") -> Path:
    """Render the demo scene and write it as a NeRF-synthetic folder at ``out_dir``.

    Everything is written into a temporary sibling folder that is renamed into place at the end,
    so a failure leaves nothing behind (not even parent folders this call created).

    Args:
        out_dir: folder to create; it must not exist unless ``overwrite``.
        width, height: image size in pixels (small by default: the CPU demo trains in minutes).
        n_train, n_test: number of train and test views.
        seed: turns and jitters the cameras; the same seed gives the same files on the same device.
        supersample: each pixel averages ``supersample**2`` rays (anti-aliasing, fractional alpha).
        overwrite: replace an existing ``out_dir``.
        device: where the views are rendered ("cpu" or "cuda").

    Returns:
        The folder written, as a Path.

    Raises:
        DataError: ``out_dir`` exists (without ``overwrite``) or cannot be written.
    """
    check_positive_ints(width=width, height=height, n_train=n_train, n_test=n_test, supersample=supersample)

    def render(c2w: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
        return render_demo_views(c2w.to(device), intrinsics.to(device), width, height, supersample).cpu()

    return write_rendered_scene(out_dir, overwrite, "the demo scene", demo_cameras(n_train, n_test, seed), width,
                                height, CAMERA_ANGLE_X, render, {},
                                _scene_description(width, height, n_train, n_test, seed, supersample))


# ---- the demo scene in a textured room (for structure from motion) --------------------------
ROOM_FLOOR = -0.5  # z of the floor, just under the objects
ROOM_RADIUS = 6.0  # radius of the room's cylindrical wall (about z), beyond every camera
ROOM_TEXELS = (170.0, 64.0)  # texels per scene unit of the floor's and the wall's textures
ROOM_WALL_HEIGHT = 6.0  # textured height of the wall above the floor (higher up it repeats, mirrored)
ROOM_CELLS = (4, 8, 16, 32, 64)  # value-noise octaves: lattice spacing in texels


def _value_noise(height: int, width: int, generator: torch.Generator) -> torch.Tensor:
    """[3, height, width] float32 in [0, 1]: octaves of bicubic value noise, mostly grey (SIFT
    works on intensity), each octave weighted by its lattice spacing, contrast-stretched."""
    noise = torch.zeros(1, 3, height, width)
    for cells in ROOM_CELLS:
        lattice = torch.rand(1, 3, height // cells + 2, width // cells + 2, generator=generator)
        lattice[:, 1:] = 0.6 * lattice[:, :1] + 0.4 * lattice[:, 1:]  # green, blue follow red
        up = torch.nn.functional.interpolate(lattice, scale_factor=cells, mode="bicubic", align_corners=False)
        noise += cells ** 0.5 * up[..., :height, :width]
    noise = noise - noise.mean(dim=(2, 3), keepdim=True)
    return (0.5 + noise[0] / (3.0 * noise.std())).clamp(0.0, 1.0)


def _room_colour(origin: torch.Tensor, d: torch.Tensor, floor: torch.Tensor, wall: torch.Tensor,
                 radius: float) -> torch.Tensor:
    """Colour [N, 3] where rays (``origin`` [3], directions ``d`` [N, 3]) meet the room: the
    floor z = F (t = (F - o_z) / d_z) or the wall |o_xy + t d_xy| = R (R = ``radius``), whichever
    is nearer."""
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = origin[0] * d[:, 0] + origin[1] * d[:, 1]
    c = origin[0] ** 2 + origin[1] ** 2 - radius ** 2  # < 0: the camera is inside
    t_wall = (-b + torch.sqrt(b * b - a * c)) / a.clamp_min(1e-12)
    t_floor = torch.where(d[:, 2] < 0, (ROOM_FLOOR - origin[2]) / d[:, 2].clamp(max=-1e-12), math.inf)
    p = origin + torch.minimum(t_wall, t_floor)[:, None] * d
    on_floor = t_floor < t_wall
    floor_uv = p[:, :2] / radius  # grid_sample's [-1, 1] spans the floor's square
    arc = torch.atan2(p[:, 1], p[:, 0]) / math.pi
    wall_uv = torch.stack([arc, 2.0 * (p[:, 2] - ROOM_FLOOR) / ROOM_WALL_HEIGHT - 1.0], -1)

    def sample(texture: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
        grid = uv.reshape(1, 1, -1, 2).float()
        return torch.nn.functional.grid_sample(texture[None], grid, align_corners=False,
                                               padding_mode="reflection")[0, :, 0].T

    return torch.where(on_floor[:, None], sample(floor, floor_uv), sample(wall, wall_uv))


def render_room_views(c2w: torch.Tensor, intrinsics: torch.Tensor, width: int, height: int,
                      supersample: int = 2, seed: int = 0, radius: float = ROOM_RADIUS) -> torch.Tensor:
    """The demo scene standing in a room whose floor and wall carry multi-scale noise, as a
    photograph of it would look: the objects' own textures are too plain for feature matching.

    The floor (z = ``ROOM_FLOOR``) lies under every object and the wall (radius ``radius``)
    beyond them, so for a camera inside the room each ray meets the room only behind the
    objects: rgb = alpha c_objects + (1 - alpha) c_room, where c_room is the mean over all of the
    pixel's rays (exact but at the objects' outlines). Each pixel averages ``supersample``²
    stratified rays, the same rays :func:`render_demo_views` traces.

    Args:
        c2w: [V, 3, 4] float32 camera-to-world, OpenGL convention, on the CPU; every camera
            inside the room (above the floor, within the wall).
        intrinsics: [V, 4] float32 fx, fy, cx, cy in pixels.
        width, height: image size in pixels.
        supersample: ss, rays per pixel side.
        seed: picks the room's noise.
        radius: the wall's radius in scene units (the floor's texture spans its square).

    Returns:
        [V, H, W, 3] float32 RGB in [0, 1].
    """
    objects = render_demo_views(c2w, intrinsics, width, height, supersample)  # validates the arguments
    origins = c2w[:, :, 3].double()
    if (origins[:, 2] <= ROOM_FLOOR).any() or (origins[:, :2].norm(dim=1) >= radius).any():
        raise ValueError(f"every camera must be inside the room (z > {ROOM_FLOOR}, |xy| < {radius})")
    generator = torch.Generator().manual_seed(seed)
    side = int(2 * radius * ROOM_TEXELS[0])
    floor = _value_noise(side, side, generator)
    wall_texels = (int(ROOM_WALL_HEIGHT * ROOM_TEXELS[1]), int(2 * math.pi * radius * ROOM_TEXELS[1]))
    wall = _value_noise(*wall_texels, generator)
    ss = supersample
    sub = (torch.arange(ss, dtype=torch.float64) + 0.5) / ss
    u = (torch.arange(width, dtype=torch.float64)[:, None] + sub).reshape(-1)
    w = (torch.arange(height, dtype=torch.float64)[:, None] + sub).reshape(-1)
    room = torch.empty(len(c2w), height, width, 3)
    for v, (m, (fx, fy, cx, cy)) in enumerate(zip(c2w.double(), intrinsics.double())):
        y, x = torch.meshgrid(-(w - cy) / fy, (u - cx) / fx, indexing="ij")
        d = torch.stack([x, y, -torch.ones_like(x)], -1).reshape(-1, 3) @ m[:, :3].T
        d = d / d.norm(dim=1, keepdim=True)
        colour = _room_colour(m[:, 3], d, floor, wall, radius).reshape(height, ss, width, ss, 3)
        room[v] = colour.mean(dim=(1, 3)).float()
    alpha = objects[..., 3:]
    return alpha * objects[..., :3] + (1.0 - alpha) * room
