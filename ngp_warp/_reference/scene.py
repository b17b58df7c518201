"""Float64 pure-torch twin of ``kernels/scene.py`` (the demo scene's sphere tracer)."""

from __future__ import annotations

import math

import torch

from ngp_warp.kernels import scene as K


def _vec(values) -> torch.Tensor:
    return torch.tensor(values, dtype=torch.float64)


def _box_local(p: torch.Tensor) -> torch.Tensor:
    q = p - _vec(K.BOX_CENTER)
    c, s = math.cos(K.BOX_ANGLE), math.sin(K.BOX_ANGLE)
    return torch.stack([c * q[:, 0] + s * q[:, 1], -s * q[:, 0] + c * q[:, 1], q[:, 2]], -1)


def object_distances(p: torch.Tensor) -> torch.Tensor:
    """[R, 3] points -> [R, 4] signed distances to sphere, box, torus, cylinder."""
    sphere = (p - _vec(K.SPHERE_CENTER)).norm(dim=-1) - K.SPHERE_RADIUS
    d = _box_local(p).abs() - (_vec(K.BOX_HALF) - K.BOX_ROUND)
    box = d.clamp_min(0).norm(dim=-1) + d.max(dim=-1).values.clamp_max(0) - K.BOX_ROUND
    q = p - _vec(K.TORUS_CENTER)
    a = q[:, :2].norm(dim=-1) - K.TORUS_MAJOR
    torus = torch.sqrt(a * a + q[:, 2] ** 2) - K.TORUS_MINOR
    q = p - _vec(K.CYL_CENTER)
    dr = q[:, :2].norm(dim=-1) - (K.CYL_RADIUS - K.CYL_ROUND)
    dz = q[:, 2].abs() - (K.CYL_HALF_HEIGHT - K.CYL_ROUND)
    cyl = torch.maximum(dr, dz).clamp_max(0) + torch.sqrt(dr.clamp_min(0) ** 2 + dz.clamp_min(0) ** 2) - K.CYL_ROUND
    return torch.stack([sphere, box, torus, cyl], -1)


def scene_sdf(p: torch.Tensor) -> torch.Tensor:
    return object_distances(p).min(dim=-1).values


def _parity(x: torch.Tensor) -> torch.Tensor:
    return torch.floor(x) - 2 * torch.floor(0.5 * x)


def albedo(p: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """[R, 3] surface points, [R] object ids -> [R, 3] texture colours."""
    q = p - _vec(K.SPHERE_CENTER)
    q = q / q.norm(dim=-1, keepdim=True)
    u = (torch.atan2(q[:, 1], q[:, 0]) / (2 * math.pi) + 0.5) * K.CHECKER_CELLS[0]
    v = torch.acos(q[:, 2].clamp(-1, 1)) / math.pi * K.CHECKER_CELLS[1]
    t = _parity(torch.floor(u) + torch.floor(v))[:, None]
    checker = _vec(K.CHECKER_A) * (1 - t) + _vec(K.CHECKER_B) * t
    t = _parity(_box_local(p)[:, 0] / K.STRIPE_WIDTH)[:, None]
    stripes = _vec(K.STRIPE_A) * (1 - t) + _vec(K.STRIPE_B) * t
    q = p - _vec(K.TORUS_CENTER)
    phi = torch.atan2(q[:, 1], q[:, 0])[:, None] + _vec([0.0, 2 * math.pi / 3, 4 * math.pi / 3])
    hue = K.HUE_BIAS + K.HUE_GAIN * torch.cos(phi)
    t = ((p[:, 2] - K.CYL_CENTER[2] + K.CYL_HALF_HEIGHT) / (2 * K.CYL_HALF_HEIGHT)).clamp(0, 1)[:, None]
    gradient = _vec(K.GRADIENT_BOTTOM) * (1 - t) + _vec(K.GRADIENT_TOP) * t
    options = torch.stack([checker, stripes, hue, gradient], 1)  # [R, 4, 3]
    return options[torch.arange(len(k)), k]


def shade(p: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """[R, 3] hit points and ray directions -> [R, 3] colours in [0, 1]."""
    k = object_distances(p).argmin(dim=-1)
    e = K.NORMAL_EPS
    g = torch.zeros_like(p)
    for s in ([1.0, -1.0, -1.0], [-1.0, -1.0, 1.0], [-1.0, 1.0, -1.0], [1.0, 1.0, 1.0]):
        s = _vec(s)
        g = g + s * scene_sdf(p + e * s)[:, None]
    n = g / g.norm(dim=-1, keepdim=True)
    light = _vec(K.LIGHT_DIR)
    diff = (n @ light).clamp_min(0)[:, None]
    h = light - d
    h = h / h.norm(dim=-1, keepdim=True)
    spec = _vec(K.SPECULAR)[k] * (n * h).sum(-1).clamp_min(0) ** _vec(K.SHININESS)[k]
    return (albedo(p, k) * (K.AMBIENT + K.DIFFUSE * diff) + spec[:, None]).clamp(0, 1)


def trace(o: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """[R, 3] rays -> (hit [R] bool, t [R]) by sphere tracing inside [-BOUND, BOUND]^3."""
    ta = (-K.BOUND - o) / d
    tb = (K.BOUND - o) / d
    t0 = torch.minimum(ta, tb).max(dim=-1).values.clamp_min(0)
    t1 = torch.maximum(ta, tb).min(dim=-1).values.clamp_max(1e30)
    t = t0.clone()
    active = t0 < t1
    hit = torch.zeros_like(active)
    for _ in range(K.MAX_STEPS):
        active = active & (t <= t1)
        f = scene_sdf(o + t[:, None] * d)
        new_hit = active & (f < K.HIT_EPS)
        hit = hit | new_hit
        active = active & ~new_hit
        t = torch.where(active, t + f, t)
    return hit, t


def view_rays(c2w: torch.Tensor, intrinsics: torch.Tensor, width: int, height: int,
              ss: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The ss x ss stratified rays of every pixel of every view, float64: origins and unit
    directions [V * H * W * ss², 3], views, then rows, columns and sub-samples, in that order."""
    c2w, intrinsics = c2w.double(), intrinsics.double()
    v, py, px, sy, sx = torch.meshgrid(
        torch.arange(len(c2w)), torch.arange(height), torch.arange(width), torch.arange(ss), torch.arange(ss),
        indexing="ij")
    v, py, px, sy, sx = (t.reshape(-1) for t in (v, py, px, sy, sx))
    fx, fy, cx, cy = intrinsics[v].unbind(-1)
    x = (px + (sx + 0.5) / ss - cx) / fx
    y = -(py + (sy + 0.5) / ss - cy) / fy
    rot = c2w[v, :, :3]
    d = rot[:, :, 0] * x[:, None] + rot[:, :, 1] * y[:, None] - rot[:, :, 2]
    return c2w[v, :, 3], d / d.norm(dim=-1, keepdim=True)


def render_views(c2w: torch.Tensor, intrinsics: torch.Tensor, width: int, height: int, ss: int) -> torch.Tensor:
    """Twin of ``kernels.scene.render_views``: [V, 3, 4], [V, 4] -> [V, H, W, 4] float64."""
    o, d = view_rays(c2w, intrinsics, width, height, ss)
    hit, t = trace(o, d)
    rgb = torch.zeros_like(o)
    rgb[hit] = shade(o[hit] + t[hit, None] * d[hit], d[hit])
    rgb = rgb.reshape(len(c2w), height, width, ss * ss, 3)
    hits = hit.reshape(len(c2w), height, width, ss * ss).double()
    n_hits = hits.sum(-1, keepdim=True)
    mean = rgb.sum(-2) / n_hits.clamp_min(1)
    return torch.cat([mean, n_hits / (ss * ss)], -1)
