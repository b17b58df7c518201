"""Float64 pure-torch twin of ``kernels/scene_unbounded.py`` (the unbounded 360° scene's tracer)."""

from __future__ import annotations

import math

import torch

from ngp_warp._reference import scene as objects
from ngp_warp.kernels import scene as S
from ngp_warp.kernels import scene_unbounded as K


def _vec(values) -> torch.Tensor:
    return torch.tensor(values, dtype=torch.float64)


def _pillar_centers() -> torch.Tensor:
    phi = K.PILLAR_PHASE + 2 * math.pi * torch.arange(K.PILLAR_COUNT, dtype=torch.float64) / K.PILLAR_COUNT
    return K.PILLAR_RING * torch.stack([torch.cos(phi), torch.sin(phi)], -1)  # [P, 2]


def pillar_hit(o: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """[R, 3] rays -> (t [R] of the nearest pillar, inf for none; index [R]; cap hit [R] bool)."""
    top = K.GROUND_Z + K.PILLAR_HEIGHT
    q = o[:, None, :2] - _pillar_centers()  # [R, P, 2]
    dxy = d[:, None, :2]
    a = (dxy * dxy).sum(-1)
    b = (q * dxy).sum(-1)
    disc = b * b - a * ((q * q).sum(-1) - K.PILLAR_RADIUS**2)
    side = (-b - disc.clamp_min(0).sqrt()) / a
    z = o[:, None, 2] + side * d[:, None, 2]
    side_ok = (a > 0) & (disc >= 0) & (side > 0) & (z >= K.GROUND_Z) & (z <= top)
    cap = ((top - o[:, 2]) / d[:, 2])[:, None].expand_as(side)
    e = q + cap[..., None] * dxy
    cap_ok = ((d[:, 2] < 0) & (o[:, 2] > top))[:, None] & ((e * e).sum(-1) <= K.PILLAR_RADIUS**2)
    inf = torch.full_like(side, math.inf)
    side, cap = torch.where(side_ok, side, inf), torch.where(cap_ok, cap, inf)
    t = torch.minimum(side, cap)  # [R, P]
    best, k = t.min(dim=-1)
    is_cap = cap.gather(1, k[:, None])[:, 0] < side.gather(1, k[:, None])[:, 0]
    return best, k, is_cap


def ground_albedo(p: torch.Tensor) -> torch.Tensor:
    r = p[:, :2].norm(dim=-1)
    fade = 1 / (1 + (r / K.GROUND_FADE) ** 2)
    s = objects._parity(torch.floor(p[:, 0] / K.GROUND_CELL) + torch.floor(p[:, 1] / K.GROUND_CELL))
    w = (0.5 + (s - 0.5) * fade)[:, None]
    return _vec(K.GROUND_A) * (1 - w) + _vec(K.GROUND_B) * w


def pillar_albedo(p: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    phi = 2 * math.pi * k.double()[:, None] / K.PILLAR_COUNT + _vec([0.0, 2 * math.pi / 3, 4 * math.pi / 3])
    hue = 0.5 + 0.4 * torch.cos(phi)
    w = 0.6 * objects._parity((p[:, 2] - K.GROUND_Z) / K.PILLAR_BAND)[:, None]
    return hue * (1 - w) + _vec(K.PILLAR_PALE) * w


def environment(d: torch.Tensor) -> torch.Tensor:
    """[R, 3] unit directions -> [R, 3] colours at infinity."""
    elevation = torch.asin(d[:, 2].clamp(-1, 1))
    phi = torch.atan2(d[:, 1], d[:, 0])
    skyline = K.SKYLINE_BASE + sum(a * torch.sin(f * phi + p) for a, f, p in K.SKYLINE_WAVES)
    w = (elevation / skyline).clamp(0, 1)[:, None]
    mountain = _vec(K.MOUNTAIN_LOW) * (1 - w) + _vec(K.MOUNTAIN_HIGH) * w
    up = d[:, 2].clamp(0, 1)
    w = (up * (2 - up))[:, None]
    sky = _vec(K.SKY_HORIZON) * (1 - w) + _vec(K.SKY_ZENITH) * w
    return torch.where((elevation < skyline)[:, None], mountain, sky)


def _lambert(albedo: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    return albedo * (S.AMBIENT + S.DIFFUSE * (n @ _vec(S.LIGHT_DIR)).clamp_min(0))[:, None]


def radiance(o: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """[R, 3] float64 rays (d unit) -> (colour [R, 3], t [R] of the first hit or MISS)."""
    hit, t_obj = objects.trace(o, d)
    t_obj = torch.where(hit, t_obj, math.inf)
    t_ground = torch.where(d[:, 2] < 0, (K.GROUND_Z - o[:, 2]) / d[:, 2], math.inf)
    t_ground = torch.where(t_ground > 0, t_ground, math.inf)
    t_pillar, k, cap = pillar_hit(o, d)
    t, what = torch.stack([t_obj, t_ground, t_pillar], -1).min(dim=-1)  # what: 0 object, 1 ground, 2 pillar
    sky = torch.isinf(t)
    p = o + torch.where(sky, 0.0, t)[:, None] * d
    colour = environment(d)
    m = ~sky & (what == 0)
    colour[m] = objects.shade(p[m], d[m])
    m = ~sky & (what == 1)
    colour[m] = _lambert(ground_albedo(p[m]), _vec([0.0, 0.0, 1.0]).expand(int(m.sum()), 3))
    m = ~sky & (what == 2)
    axis = _pillar_centers()[k[m]]
    n = torch.cat([p[m, :2] - axis, torch.zeros(int(m.sum()), 1, dtype=torch.float64)], -1)
    n = torch.where(cap[m, None], _vec([0.0, 0.0, 1.0]), n / n.norm(dim=-1, keepdim=True))
    colour[m] = _lambert(pillar_albedo(p[m], k[m]), n)
    return colour, torch.where(sky, K.MISS, t)


def render_views(c2w: torch.Tensor, intrinsics: torch.Tensor, width: int, height: int, ss: int) -> torch.Tensor:
    """Twin of ``kernels.scene_unbounded.render_views``: [V, 3, 4], [V, 4] -> [V, H, W, 3] float64."""
    o, d = objects.view_rays(c2w, intrinsics, width, height, ss)
    colour, _ = radiance(o, d)
    return colour.reshape(len(c2w), height, width, ss * ss, 3).mean(-2)
