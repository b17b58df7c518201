"""Camera paths for videos: nerfstudio's ``camera_path.json``, instant-ngp's ``base_cam.json``
(keyframes joined by a Catmull-Rom spline, rotations by slerp), and orbit and spiral paths
around the training cameras.

Every path comes out in the scene's world frame with OpenGL camera axes (the camera looks down
its −z axis, +y up), as the training cameras are.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from ngp_warp.data.data_error import short
from ngp_warp.data.transforms_json import NGP_OFFSET, NGP_SCALE, ngp_scale_offset, read_json, transforms_file
from ngp_warp.outputs.nerfstudio_frame import from_dataparser_frame, orthonormal_error, read_dataparser_transform

MAX_FRAMES = 100_000  # a video's frames: nearly an hour at 30 fps
MAX_SIDE = 16384  # a frame's width and height in pixels
FPS_RANGE = (0.01, 1000.0)  # a GIF holds a frame at most 655 s


@dataclass
class CameraPath:
    """The cameras of a video.

    c2w: [N, 3, 4] float32 camera-to-world (OpenGL axes). intrinsics: [N, 4] float32 fx, fy,
    cx, cy in pixels. width, height: frame size in pixels. fps: frames per second.
    """

    c2w: torch.Tensor
    intrinsics: torch.Tensor
    width: int
    height: int
    fps: float

    def __post_init__(self):
        """ValueError (one line) for a path no video can be made of: frames beyond
        :data:`MAX_FRAMES`, a side beyond :data:`MAX_SIDE`, or fps outside :data:`FPS_RANGE`."""
        if not 1 <= len(self.c2w) <= MAX_FRAMES:
            raise ValueError(f"a video takes 1 to {MAX_FRAMES} frames, this path has {len(self.c2w)}")
        if not (1 <= self.width <= MAX_SIDE and 1 <= self.height <= MAX_SIDE):
            raise ValueError(f"frames of {self.width}x{self.height} pixels: each side must be 1 to {MAX_SIDE}")
        if not FPS_RANGE[0] <= self.fps <= FPS_RANGE[1]:
            raise ValueError(f"{self.fps:g} frames per second: a video takes {FPS_RANGE[0]:g} to {FPS_RANGE[1]:g}")



def _intrinsics_from_fov(fov_y_deg: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """[N] vertical fields of view in degrees → [N, 4] fx = fy = H / (2 tan(fov / 2)), centred."""
    f = 0.5 * height / torch.tan(torch.deg2rad(fov_y_deg.double()) / 2)
    return torch.stack([f, f, torch.full_like(f, width / 2), torch.full_like(f, height / 2)], -1).float()


# ---- quaternions (x, y, z, w), float64 ---------------------------------------------------------

def matrix_from_quat(q: torch.Tensor) -> torch.Tensor:
    """[..., 4] quaternions (x, y, z, w; normalised here) → [..., 3, 3] rotation matrices."""
    x, y, z, w = torch.nn.functional.normalize(q.double(), dim=-1).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(*q.shape[:-1], 3, 3)


def quat_from_matrix(m: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3] rotation matrices → [..., 4] unit quaternions (x, y, z, w), w >= 0, from the
    largest of the four candidate denominators (stable for every rotation)."""
    m = m.double()
    trace = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    candidates = torch.stack([
        torch.stack([1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2], m[..., 0, 1] + m[..., 1, 0],
                     m[..., 0, 2] + m[..., 2, 0], m[..., 2, 1] - m[..., 1, 2]], -1),
        torch.stack([m[..., 0, 1] + m[..., 1, 0], 1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
                     m[..., 1, 2] + m[..., 2, 1], m[..., 0, 2] - m[..., 2, 0]], -1),
        torch.stack([m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1],
                     1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2], m[..., 1, 0] - m[..., 0, 1]], -1),
        torch.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1],
                     1 + trace], -1),
    ], -2)  # [..., 4 candidates, 4]; candidate k has 4 q_k² in its k-th entry
    best = torch.stack([candidates[..., k, k] for k in range(4)], -1).argmax(-1)
    q = torch.gather(candidates, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    q = torch.nn.functional.normalize(q, dim=-1)
    return torch.where(q[..., 3:] < 0, -q, q)


def slerp(q0: torch.Tensor, q1: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Spherical interpolation of unit quaternions [..., 4] along the shorter arc; ``t`` [...]
    may leave [0, 1] (extrapolation along the same great circle).

    .. math:: q(t) = \\frac{\\sin((1 - t)\\theta)\\, q_0 + \\sin(t\\theta)\\, q_1}{\\sin\\theta},
        \\quad \\cos\\theta = |q_0 \\cdot q_1|
    """
    dot = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(dot < 0, -q1, q1)
    dot = dot.abs().clamp(max=1.0)
    theta = torch.acos(dot)
    t = t[..., None]
    small = theta < 1e-6
    sin = torch.sin(theta).clamp_min(1e-12)
    a = torch.where(small, 1 - t, torch.sin((1 - t) * theta) / sin)
    b = torch.where(small, t, torch.sin(t * theta) / sin)
    return torch.nn.functional.normalize(a * q0 + b * q1, dim=-1)


def _lerp_key(k0: tuple, k1: tuple, t: torch.Tensor) -> tuple:
    """Keyframes (quat [M, 4], position [M, 3], fov [M]) blended at t [M]."""
    return (slerp(k0[0], k1[0], t), k0[1] + (k1[1] - k0[1]) * t[:, None], k0[2] + (k1[2] - k0[2]) * t)


def catmull_rom(quats: torch.Tensor, positions: torch.Tensor, fovs: torch.Tensor, n_frames: int,
                loop: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Uniform Catmull-Rom spline through K keyframes, evaluated at ``n_frames`` evenly spaced
    times (Barry–Goldman's pyramid of blends, as instant-ngp's ``spline_cm``, with slerp for
    rotations): it passes through every keyframe, with a continuous velocity.

    Args:
        quats: [K, 4] float64 unit quaternions (x, y, z, w). positions: [K, 3]. fovs: [K].
        loop: close the path (the last keyframe leads back to the first); otherwise the end
            keyframes are repeated as their outer neighbours and the last frame is the last key.

    Returns:
        (quats [n, 4], positions [n, 3], fovs [n]) float64.

    .. math::
        q_0 = \\mathrm{lerp}(p_0, p_1, t + 1),\\ q_1 = \\mathrm{lerp}(p_1, p_2, t),\\
        q_2 = \\mathrm{lerp}(p_2, p_3, t - 1),\\\\
        r_0 = \\mathrm{lerp}(q_0, q_1, \\tfrac{t + 1}{2}),\\ r_1 = \\mathrm{lerp}(q_1, q_2, \\tfrac{t}{2}),\\
        c(t) = \\mathrm{lerp}(r_0, r_1, t)
    """
    k = quats.shape[0]
    if k == 1 or n_frames == 1:
        return quats[:1].expand(n_frames, 4), positions[:1].expand(n_frames, 3), fovs[:1].expand(n_frames)
    spans = k if loop else k - 1
    u = torch.arange(n_frames, dtype=torch.float64) * (spans / (n_frames if loop else n_frames - 1))
    seg = u.floor().long().clamp(max=spans - 1)
    t = u - seg

    def key(offset: int) -> tuple:
        i = seg + offset
        i = i % k if loop else i.clamp(0, k - 1)
        return quats[i].double(), positions[i].double(), fovs[i].double()

    p0, p1, p2, p3 = key(-1), key(0), key(1), key(2)
    q0, q1, q2 = _lerp_key(p0, p1, t + 1), _lerp_key(p1, p2, t), _lerp_key(p2, p3, t - 1)
    return _lerp_key(_lerp_key(q0, q1, (t + 1) / 2), _lerp_key(q1, q2, t / 2), t)


# ---- files ------------------------------------------------------------------------------------

def nerfstudio_path(meta: dict, where: str) -> CameraPath:
    """nerfstudio's ``camera_path.json``: one camera per frame (``camera_to_world``: 16 floats,
    row-major 4×4, OpenGL axes; ``fov``: vertical degrees), ``render_width``/``render_height``
    and ``fps``. The matrices are taken in the scene's world frame."""
    frames = meta["camera_path"]
    kind = meta.get("camera_type", "perspective")
    if kind != "perspective":  # fisheye, equirectangular, omnidirectional, vr180: other ray models
        raise ValueError(f"{where}: camera_type {short(kind)}: only perspective paths render here")
    if not isinstance(frames, list) or not frames:
        raise ValueError(f"{where}: camera_path must be a non-empty list of cameras")
    try:
        m = torch.tensor([f["camera_to_world"] for f in frames], dtype=torch.float64)
        fov = torch.tensor([float(f["fov"]) for f in frames], dtype=torch.float64)
        height = int(meta["render_height"])
        width = int(meta.get("render_width") or round(height * float(frames[0]["aspect"])))
        fps = float(meta.get("fps", 24.0))
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{where}: not a nerfstudio camera path ({type(e).__name__}: {e})") from None
    if m.shape[1:] != (16,) or not torch.isfinite(m).all():
        raise ValueError(f"{where}: camera_to_world must hold 16 finite numbers per camera")
    m = m.reshape(-1, 4, 4)
    rotation = m[:, :3, :3]
    error = orthonormal_error(rotation)
    bottom = (m[:, 3] - torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)).abs().amax(1)
    if (error > 0.02).any() or (bottom > 1e-6).any():  # as training's poses: a rigid pose, row 4 = 0 0 0 1
        k = int(torch.nonzero((error > 0.02) | (bottom > 1e-6))[0])
        raise ValueError(f"{where}: camera {k}'s camera_to_world is not a rigid camera pose (orthonormal "
                         f"rotation, bottom row 0 0 0 1)")
    if not (width > 0 and height > 0 and fps > 0 and ((fov > 0) & (fov < 180)).all()):
        raise ValueError(f"{where}: render size, fps and fov must be positive (fov under 180 degrees)")
    return CameraPath(m[:, :3].float(), _intrinsics_from_fov(fov, width, height), width, height, fps)


def ngp_transform(scene: str | Path) -> tuple[float, list[float]]:
    """(scale, offset) of instant-ngp's map ``ngp = world · scale + offset`` for a scene (a
    transforms file, or a folder with transforms.json or transforms_train.json), as training
    reads them (:func:`~ngp_warp.data.transforms_json.ngp_scale_offset`: ``scale``, ``offset``
    or ``aabb``), else instant-ngp's defaults 0.33 and (0.5, 0.5, 0.5)."""
    path = transforms_file(scene)
    return (NGP_SCALE, list(NGP_OFFSET)) if path is None else ngp_scale_offset(read_json(path), path)


def ngp_to_world(rotation: torch.Tensor, position: torch.Tensor, scale: float, offset) -> tuple[torch.Tensor, torch.Tensor]:
    """instant-ngp's ``ngp_matrix_to_nerf``: cameras in its unit-cube frame (rows cycled
    xyz → yzx, camera looking down +z with +y down) → world frame, OpenGL axes.

    rotation [K, 3, 3], position [K, 3] → (rotation [K, 3, 3], position [K, 3]) float64,

    .. math:: R_w = P R\\,\\mathrm{diag}(1, -1, -1),\\quad t_w = (P t - o) / s,\\quad
        P = \\text{rows } (2, 0, 1)
    """
    cycle = [2, 0, 1]
    r = rotation.double()[:, cycle] * torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)
    t = (position.double()[:, cycle] - torch.as_tensor(offset, dtype=torch.float64)) / scale
    return r, t


def instant_ngp_path(meta: dict, where: str, width: int, height: int, n_frames: int, fps: float,
                     scale: float = NGP_SCALE, offset=NGP_OFFSET) -> CameraPath:
    """instant-ngp's ``base_cam.json``: keyframes ``path`` of {``R``: quaternion [x, y, z, w],
    ``T``: position, ``fov``: vertical degrees} in its unit-cube frame (see :func:`ngp_to_world`),
    optionally ``loop``; joined by :func:`catmull_rom` into ``n_frames`` frames."""
    keys = meta["path"]
    if not isinstance(keys, list) or not keys:
        raise ValueError(f"{where}: path must be a non-empty list of keyframes")
    try:
        quats = torch.tensor([k["R"] for k in keys], dtype=torch.float64)
        positions = torch.tensor([k["T"] for k in keys], dtype=torch.float64)
        fovs = torch.tensor([float(k["fov"]) for k in keys], dtype=torch.float64)
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{where}: not an instant-ngp camera path ({type(e).__name__}: {e})") from None
    if quats.shape[1:] != (4,) or positions.shape[1:] != (3,) or not torch.isfinite(quats).all() \
            or (quats.norm(dim=-1) == 0).any() or not torch.isfinite(positions).all():
        raise ValueError(f"{where}: each keyframe needs R (4 numbers, not all 0) and T (3 numbers)")
    if not ((fovs > 0) & (fovs < 180)).all():
        raise ValueError(f"{where}: fov must be in (0, 180) degrees")
    rotation, position = ngp_to_world(matrix_from_quat(quats), positions, scale, offset)
    q, t, fov = catmull_rom(quat_from_matrix(rotation), position, fovs, n_frames, loop=bool(meta.get("loop", False)))
    c2w = torch.cat([matrix_from_quat(q), t[:, :, None]], -1).float()
    return CameraPath(c2w, _intrinsics_from_fov(fov, width, height), width, height, fps)


def load_camera_path(path: str | Path, width: int, height: int, n_frames: int, fps: float,
                     scale: float = NGP_SCALE, offset=NGP_OFFSET, dataparser: str | Path | None = None,
                     scene: str | Path | None = None) -> CameraPath:
    """Read a nerfstudio ``camera_path.json`` (its own size, fps and frames; with ``dataparser``,
    nerfstudio's ``dataparser_transforms.json``, taken from the frame nerfstudio trained in back
    to the ``scene`` file's, see :func:`read_dataparser_transform`) or an instant-ngp
    ``base_cam.json`` (``width`` × ``height``, ``n_frames`` at ``fps``, instant-ngp's unit-cube
    map ``scale``/``offset``, see :func:`ngp_transform`). Raises ValueError with one line."""
    path = Path(path)
    meta = read_json(path)  # a DataError, a ValueError, names a file that cannot be read
    if dataparser is not None and "camera_path" not in meta:
        raise ValueError(f"{path}: a dataparser transform maps nerfstudio camera paths only")
    if "camera_path" in meta:
        cameras = nerfstudio_path(meta, str(path))
        if dataparser is None:
            return cameras
        back = read_dataparser_transform(dataparser, scene)
        return replace(cameras, c2w=from_dataparser_frame(cameras.c2w, *back).float())
    if "path" in meta:
        return instant_ngp_path(meta, str(path), width, height, n_frames, fps, scale, offset)
    raise ValueError(f"{path}: neither a nerfstudio camera_path.json (camera_path) nor an "
                     f"instant-ngp base_cam.json (path)")


# ---- paths around the training cameras ---------------------------------------------------------

def _look_at(position: torch.Tensor, center: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    """[3, 4] OpenGL camera-to-world at ``position`` looking at ``center`` with ``up`` up."""
    back = (position - center) / (position - center).norm().clamp_min(1e-12)  # camera +z, away
    right = torch.linalg.cross(up, back)
    right = right / right.norm().clamp_min(1e-12)
    return torch.stack([right, torch.linalg.cross(back, right), back, position], dim=1)


def _frame(c2w: torch.Tensor, center: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(up, first camera's horizontal direction, its sideways companion) around ``center``: up
    is the cameras' mean up axis."""
    up = c2w[:, :3, 1].mean(0)
    up = up / up.norm().clamp_min(1e-12)
    start = c2w[0, :3, 3] - center
    ahead = start - (start @ up) * up
    ahead = ahead / ahead.norm().clamp_min(1e-12)
    return up, ahead, torch.linalg.cross(up, ahead)


def orbit_cameras(c2w: torch.Tensor, center: torch.Tensor, n_frames: int) -> torch.Tensor:
    """[n_frames, 3, 4] float32 cameras circling ``center`` about the cameras' mean up axis,
    starting at the first camera (its height and distance), looking at the centre.

    c2w: [N, 3, 4] float cameras (OpenGL axes). center: [3] float."""
    c2w, center = c2w.double().cpu(), torch.as_tensor(center, dtype=torch.float64).cpu()
    up, ahead, side = _frame(c2w, center)
    start = c2w[0, :3, 3] - center
    height, radius = start @ up, (start - (start @ up) * up).norm()
    frames = []
    for k in range(n_frames):
        a = 2 * math.pi * k / n_frames
        pos = center + height * up + radius * (math.cos(a) * ahead + math.sin(a) * side)
        frames.append(_look_at(pos, center, up))
    return torch.stack(frames).float()


def spiral_cameras(c2w: torch.Tensor, center: torch.Tensor, n_frames: int, turns: float = 2.0) -> torch.Tensor:
    """[n_frames, 3, 4] float32 cameras on ``turns`` turns about the cameras' mean up axis at
    their median distance from ``center``, the elevation swinging once down and up between the
    10th and 90th percentile of the cameras' elevations, looking at the centre; it starts
    above the first camera's azimuth and ends where it began (a seamless loop for whole turns).

    c2w: [N, 3, 4] float cameras (OpenGL axes). center: [3] float."""
    c2w, center = c2w.double().cpu(), torch.as_tensor(center, dtype=torch.float64).cpu()
    up, ahead, side = _frame(c2w, center)
    offsets = c2w[:, :3, 3] - center
    radius = offsets.norm(dim=-1).median()
    elevation = torch.asin((offsets @ up / offsets.norm(dim=-1).clamp_min(1e-12)).clamp(-1, 1))
    low, high = torch.quantile(elevation, 0.1), torch.quantile(elevation, 0.9)
    frames = []
    for k in range(n_frames):
        s = k / n_frames
        a, e = 2 * math.pi * turns * s, low + (high - low) * (0.5 + 0.5 * math.cos(2 * math.pi * s))
        horizontal = math.cos(a) * ahead + math.sin(a) * side
        frames.append(_look_at(center + radius * (torch.cos(e) * horizontal + torch.sin(e) * up), center, up))
    return torch.stack(frames).float()


def around_cameras(kind: str, c2w: torch.Tensor, intrinsics: torch.Tensor, width: int, height: int,
                   center: torch.Tensor, n_frames: int, fps: float) -> CameraPath:
    """An ``"orbit"`` or ``"spiral"`` path around ``center`` from cameras c2w [N, 3, 4] with
    intrinsics [N, 4] (the first camera's are used for every frame) and their image size."""
    cameras = {"orbit": orbit_cameras, "spiral": spiral_cameras}[kind](c2w, center, n_frames)
    return CameraPath(cameras, intrinsics[0].float().cpu().expand(n_frames, 4).clone(), width, height, fps)
