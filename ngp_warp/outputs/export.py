"""Mesh and point-cloud export of a trained field (``ngp-warp export``).

Mesh: the density is sampled on a regular grid of nodes over the occupied part of the field's
box, Warp's marching cubes (``warp.geometry.IsoSurfaceMarchingCubes``, CPU or CUDA) extracts
the level set σ = threshold, triangles whose three vertices lie in empty occupancy cells are
dropped, each vertex is coloured by the field seen head-on (direction = −outward normal), and
the vertices are mapped to the scene's original frame by a 4×4 similarity ``world_from_scene``.

Points: each training ray with opacity > 0.5 gives one point at its expected depth.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import torch
import warp as wp
import warp.geometry  # noqa: F401  (registers wp.geometry)

from ngp_warp import _wp
from ngp_warp.kernels import export as K
from ngp_warp.training.memory_estimate import available_bytes
from ngp_warp.ops.occupancy import OccupancyGrid

SigmaFn = Callable[[torch.Tensor], torch.Tensor]
ColorFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


@dataclass
class Mesh:
    """A coloured triangle mesh.

    vertices: [V, 3] float32. faces: [F, 3] int64, counter-clockwise seen from outside.
    colors: [V, 3] uint8 RGB.
    """

    vertices: torch.Tensor
    faces: torch.Tensor
    colors: torch.Tensor


def occupied_box(aabb: torch.Tensor, grid: OccupancyGrid | None) -> list[float]:
    """The part of ``aabb`` ([6] float) covered by occupied cells of ``grid`` (any cascade), as
    6 floats; all of ``aabb`` when ``grid`` is None. Raises ValueError when no cell is occupied."""
    box = [float(v) for v in torch.as_tensor(aabb).reshape(6)]
    if grid is None:
        return box
    occupied = grid.occupied().cpu()
    g = torch.tensor(grid.aabb_host, dtype=torch.float64)
    centre, half = (g[:3] + g[3:]) / 2, (g[3:] - g[:3]) / 2
    lo, hi = torch.full((3,), math.inf, dtype=torch.float64), torch.full((3,), -math.inf, dtype=torch.float64)
    for level in range(grid.levels):
        ijk = occupied[level].nonzero()
        if ijk.shape[0] == 0:
            continue
        size = half * 2.0 ** (level + 1) / grid.resolution
        corner = centre - half * 2.0**level
        lo = torch.minimum(lo, corner + ijk.amin(0) * size)
        hi = torch.maximum(hi, corner + (ijk.amax(0) + 1) * size)
    if not torch.isfinite(lo).all():
        raise ValueError("the occupancy grid has no occupied cell: nothing to mesh")
    lo = torch.maximum(lo, torch.tensor(box[:3], dtype=torch.float64))
    hi = torch.minimum(hi, torch.tensor(box[3:], dtype=torch.float64))
    if not (hi > lo).all():
        raise ValueError("the occupied cells lie outside the field's box: nothing to mesh")
    return lo.tolist() + hi.tolist()


def grid_shape(box: list[float], resolution: int) -> tuple[int, int, int]:
    """Nodes per axis: ``resolution`` along the box's longest side, cubic voxels, at least 2."""
    sides = [box[3 + a] - box[a] for a in range(3)]
    voxel = max(sides) / (resolution - 1)
    return tuple(max(2, math.ceil(s / voxel) + 1) for s in sides)


@torch.no_grad()
def density_grid(sigma_fn: SigmaFn, box: list[float], shape: tuple[int, int, int], device,
                 chunk: int = 1 << 18) -> torch.Tensor:
    """σ at the grid's nodes: [nx, ny, nz] float32 on ``device``, node (i, j, k) at
    ``lower + (i, j, k) ⊙ (upper − lower) / (shape − 1)``; ``sigma_fn`` gets chunks of at most
    ``chunk`` points [M, 3] float32 and returns [M] (or [M, 1]) densities."""
    nx, ny, nz = shape
    lower = torch.tensor(box[:3], dtype=torch.float32, device=device)
    step = (torch.tensor(box[3:], dtype=torch.float32, device=device) - lower) / torch.tensor(
        [nx - 1, ny - 1, nz - 1], dtype=torch.float32, device=device)
    out = torch.empty(nx * ny * nz, dtype=torch.float32, device=device)
    for lo in range(0, out.numel(), chunk):
        idx = torch.arange(lo, min(out.numel(), lo + chunk), device=device)
        ijk = torch.stack([idx // (ny * nz), (idx // nz) % ny, idx % nz], -1).float()
        points = (lower + ijk * step).contiguous()
        out[lo:lo + idx.numel()] = sigma_fn(points).detach().reshape(-1).float()
    return out.reshape(nx, ny, nz)


def marching_cubes(field: torch.Tensor, threshold: float, box: list[float]) -> tuple[torch.Tensor, torch.Tensor]:
    """The level set ``field = threshold`` of a [nx, ny, nz] float32 node grid over ``box``, by
    Warp's marching cubes on the field's device (torch's current stream on CUDA).

    Returns:
        vertices [V, 3] float32 and faces [F, 3] int64, counter-clockwise seen from the side
        where ``field < threshold`` (outside, for a density).
    """
    device = _wp.device_of(field)
    with wp.ScopedStream(_wp.current_stream(device)) if device != "cpu" else contextlib.nullcontext():
        verts, tris = wp.geometry.IsoSurfaceMarchingCubes.extract(
            wp.from_torch(field.contiguous(), requires_grad=False), float(threshold),
            lower=tuple(box[:3]), upper=tuple(box[3:]))
        vertices = wp.to_torch(verts, requires_grad=False).clone()
        faces = wp.to_torch(tris, requires_grad=False).reshape(-1, 3).long()
    return vertices, faces[:, [0, 2, 1]].contiguous()  # Warp winds them facing the high side


def crop_to_occupied(vertices: torch.Tensor, faces: torch.Tensor, grid: OccupancyGrid
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """Drop the triangles whose three vertices lie in empty cells of ``grid`` and the vertices
    no triangle uses. vertices [V, 3] float32, faces [F, 3] int64 (same device as the grid) →
    (vertices [V', 3], faces [F', 3]) renumbered."""
    occupied = torch.empty(vertices.shape[0], dtype=torch.uint8, device=vertices.device)
    _wp.launch(K.points_occupied, vertices.shape[0],
               [_wp.to_wp(vertices.contiguous(), dtype=wp.vec3), grid.aabb, grid.levels, grid.resolution,
                grid.bitfield, occupied], _wp.device_of(vertices))
    faces = faces[occupied.bool()[faces].any(-1)]
    used = torch.zeros(vertices.shape[0], dtype=torch.bool, device=vertices.device)
    used[faces.reshape(-1)] = True
    renumber = torch.cumsum(used, 0) - 1
    return vertices[used], renumber[faces]


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted unit normals [V, 3] of a mesh (vertices [V, 3], faces [F, 3] wound
    counter-clockwise seen from outside, so they point outwards):

    .. math:: n_v \\propto \\sum_{f \\ni v} (b_f - a_f) \\times (c_f - a_f)
    """
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    face_normal = torch.linalg.cross(b - a, c - a)
    normals = torch.zeros_like(vertices)
    for k in range(3):
        normals.index_add_(0, faces[:, k], face_normal)
    return normals / normals.norm(dim=-1, keepdim=True).clamp_min(1e-20)


@torch.no_grad()
def vertex_colors(color_fn: ColorFn, vertices: torch.Tensor, normals: torch.Tensor,
                  chunk: int = 1 << 18) -> torch.Tensor:
    """[V, 3] uint8: ``color_fn(x, d)`` ([M, 3] points, [M, 3] unit directions → [M, 3] RGB in
    [0, 1]) at each vertex seen head-on, d = −normal."""
    out = torch.empty(vertices.shape[0], 3, dtype=torch.uint8, device=vertices.device)
    for lo in range(0, vertices.shape[0], chunk):
        x = vertices[lo:lo + chunk].contiguous()
        rgb = color_fn(x, (-normals[lo:lo + chunk]).contiguous()).detach().float()
        out[lo:lo + chunk] = (rgb.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8)
    return out


def to_world(points: torch.Tensor, world_from_scene: torch.Tensor | None) -> torch.Tensor:
    """Points [N, 3] float32 mapped by a [4, 4] similarity (None: unchanged): R·p + t."""
    if world_from_scene is None:
        return points
    m = torch.as_tensor(world_from_scene, dtype=torch.float64).to(points.device)
    return (points.double() @ m[:3, :3].T + m[:3, 3]).float()


def _check_similarity(world_from_scene) -> None:
    if world_from_scene is None:
        return
    m = torch.as_tensor(world_from_scene, dtype=torch.float64).cpu()
    if m.shape != (4, 4) or not torch.isfinite(m).all():
        raise ValueError(f"world_from_scene must be a finite [4, 4] matrix, got shape {list(m.shape)}")
    r = m[:3, :3]
    scale2 = torch.linalg.det(r).abs() ** (2.0 / 3.0)
    if scale2 == 0 or not torch.allclose(r @ r.T, scale2 * torch.eye(3, dtype=torch.float64), atol=1e-5 * float(scale2)):
        raise ValueError("world_from_scene must be a similarity (scaled rotation and translation)")


MESH_BYTES_PER_NODE = 16  # σ (float32) and marching cubes' per-cell counts and offsets


def _check_mesh_fits(shape: tuple[int, int, int], device: torch.device) -> None:
    """ValueError (one line) when a density grid of ``shape`` nodes and its marching cubes would
    not fit in the memory free on ``device``."""
    need, free = math.prod(shape) * MESH_BYTES_PER_NODE, available_bytes(device)
    if need > free:
        raise ValueError(f"a {shape[0]}×{shape[1]}×{shape[2]} density grid needs about {need / 1e9:.3g} GB but "
                         f"{device} has {free / 1e9:.3g} GB free: lower the resolution")


def extract_mesh(sigma_fn: SigmaFn, color_fn: ColorFn, aabb: torch.Tensor, *, threshold: float,
                 resolution: int = 256, grid: OccupancyGrid | None = None,
                 world_from_scene: torch.Tensor | None = None, chunk: int = 1 << 18) -> Mesh:
    """Mesh the level set σ = ``threshold`` of a field.

    Args:
        sigma_fn: points [M, 3] float32 → σ [M] (scene units), on the device of ``aabb``.
        color_fn: points [M, 3], unit view directions [M, 3] → RGB [M, 3] in [0, 1].
        aabb: [6] float32, the field's box (xmin, ymin, zmin, xmax, ymax, zmax), on the device
            everything runs on.
        threshold: σ of the surface (> 0).
        resolution: grid nodes along the longest side of the marched box (>= 2).
        grid: occupancy grid: the marched box shrinks to its occupied cells, and triangles in
            empty cells are dropped. None: the whole box, nothing dropped.
        world_from_scene: [4, 4] similarity to the scene's original frame (None: identity).

    Returns:
        :class:`Mesh` on the device of ``aabb``, in the original frame.

    Raises:
        ValueError: bad arguments, or no surface at this threshold.
    """
    if not (isinstance(resolution, int) and resolution >= 2):
        raise ValueError(f"resolution must be an int >= 2, got {resolution!r}")
    if not (isinstance(threshold, (int, float)) and math.isfinite(threshold) and threshold > 0):
        raise ValueError(f"threshold must be a positive number, got {threshold!r}")
    _check_similarity(world_from_scene)
    box = occupied_box(aabb, grid)
    shape = grid_shape(box, resolution)
    _check_mesh_fits(shape, aabb.device)
    field = density_grid(sigma_fn, box, shape, aabb.device, chunk)
    vertices, faces = marching_cubes(field, threshold, box)
    if grid is not None and faces.shape[0] > 0:
        vertices, faces = crop_to_occupied(vertices, faces, grid)
    if faces.shape[0] == 0:
        raise ValueError(f"no surface at σ = {threshold:g} (the sampled σ ranges over "
                         f"[{float(field.min()):.3g}, {float(field.max()):.3g}]): try another threshold")
    colors = vertex_colors(color_fn, vertices, vertex_normals(vertices, faces), chunk)
    if world_from_scene is not None and torch.linalg.det(torch.as_tensor(world_from_scene, dtype=torch.float64)[:3, :3]) < 0:
        faces = faces[:, [0, 2, 1]]  # a mirroring map keeps the faces facing out
    return Mesh(to_world(vertices, world_from_scene), faces, colors)


def point_cloud(rays_o: torch.Tensor, rays_d: torch.Tensor, depth: torch.Tensor, opacity: torch.Tensor,
                rgb: torch.Tensor, min_opacity: float = 0.5,
                world_from_scene: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """One point per ray that is at least ``min_opacity`` opaque, at its expected depth.

    Args:
        rays_o, rays_d: [N, 3] float32 origins and unit directions (scene frame).
        depth: [N] float32, the rendered depth Σ w_i t_i (not yet divided by the opacity).
        opacity: [N] float32, Σ w_i.
        rgb: [N, 3] float32 in [0, 1].

    Returns:
        points [M, 3] float32 in the original frame and colours [M, 3] uint8,

    .. math:: p = o + d \\cdot \\frac{\\sum_i w_i t_i}{\\sum_i w_i}
    """
    n = rays_o.shape[0]
    for name, t, shape in (("rays_o", rays_o, (n, 3)), ("rays_d", rays_d, (n, 3)), ("depth", depth, (n,)),
                           ("opacity", opacity, (n,)), ("rgb", rgb, (n, 3))):
        if not isinstance(t, torch.Tensor) or tuple(t.shape) != shape:
            raise ValueError(f"{name} must be a tensor of shape {list(shape)}")
    _check_similarity(world_from_scene)
    keep = opacity > min_opacity
    t = depth[keep] / opacity[keep]
    points = rays_o[keep] + rays_d[keep] * t[:, None]
    colors = (rgb[keep].clamp(0, 1) * 255.0 + 0.5).to(torch.uint8)
    return to_world(points.float(), world_from_scene), colors


# ---- command line: ngp-warp export --------------------------------------------------------------

NGP_MESH_THRESHOLD = 2.5  # instant-ngp's marching-cubes σ, per length of its unit cube


def default_threshold(scene) -> float:
    """instant-ngp's σ threshold 2.5 per unit-cube length, in the scene's units: 2.5 over the
    longest side of the finest cascade's box (instant-ngp's unit cube)."""
    box = scene.occupancy_aabb
    return NGP_MESH_THRESHOLD / float((box[3:] - box[:3]).max())


def training_points(trainer, max_points: int, world_from_scene=None, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Points [M, 3] float32 and colours [M, 3] uint8 from every training view rendered by
    ``trainer`` (:func:`point_cloud` of its rays; a run with camera refinement renders each
    view from its refined pose), at most ``max_points`` drawn uniformly."""
    from ngp_warp.data.loading import image_rays

    split = replace(trainer.scene.train.to(trainer.device), c2w=trainer.training_c2w())
    points, colors = [], []
    for i in range(len(split)):
        out = trainer.render_image(**split.camera(i))
        rays_o, rays_d = image_rays(split, i)
        p, c = point_cloud(rays_o, rays_d, out["depth"].reshape(-1), out["opacity"].reshape(-1),
                           out["rgb"].reshape(-1, 3), world_from_scene=world_from_scene)
        points.append(p.cpu())
        colors.append(c.cpu())
    points, colors = torch.cat(points), torch.cat(colors)
    if points.shape[0] > max_points:
        keep = torch.randperm(points.shape[0], generator=torch.Generator().manual_seed(seed))[:max_points]
        points, colors = points[keep], colors[keep]
    return points, colors
