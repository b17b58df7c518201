"""Scenes on disk: NeRF-synthetic folders and instant-ngp ``transforms.json``.

* NeRF-synthetic: ``transforms_train.json`` (+ ``transforms_test.json``), ``camera_angle_x``,
  RGBA PNGs named without extension; the field lives in [-1.5, 1.5]^3.
* instant-ngp: ``transforms.json`` (or split files carrying instant-ngp keys) with ``fl_x``,
  ``fl_y``, ``cx``, ``cy``, ``w``, ``h``, ``camera_angle_x/y``, ``x_fov/y_fov``, OpenCV ``k1``,
  ``k2``, ``p1``, ``p2``, ``aabb_scale``, ``scale``, ``offset``, ``aabb``; every camera key may be
  overridden per frame. instant-ngp maps world p to its unit cube as p * scale + offset (default
  0.33 and 0.5) and lets the field fill [0.5 - aabb_scale/2, 0.5 + aabb_scale/2]^3 there; the
  scene stays in world coordinates (the transform matrices as given) and ``Scene.aabb`` is that
  box mapped back to the world.

Every problem with the files raises :class:`DataError`, one line naming the file and the problem.
"""

from __future__ import annotations

import json
import math
import os
import re
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from ngp_warp.cameras import generate_rays

__all__ = ["DataError", "Split", "Scene", "load_scene", "generate_rays", "image_rays"]

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
NGP_SCALE = 0.33  # instant-ngp's default world -> unit-cube scale (NERF_SCALE)
NGP_OFFSET = (0.5, 0.5, 0.5)
NERF_SYNTHETIC_BOUND = 1.5
NEAR_IN_UNIT_CUBE = 0.1  # near distance, in instant-ngp unit-cube lengths
_NGP_SCENE_KEYS = ("aabb_scale", "scale", "offset", "aabb")
MAX_AABB_SCALE = 2**15          # 16 occupancy cascades
_UNSUPPORTED_LENS_KEYS = ("is_fisheye", "k3", "k4", "ftheta_p0", "latlong", "equirectangular")


class DataError(ValueError):
    """A scene on disk is missing or malformed; ``str(e)`` is one line naming the file and the problem."""

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).split()))


@dataclass
class Split:
    """The images and cameras of one split.

    Attributes:
        images: [N, H, W, C] uint8, C = 3 (RGB) or 4 (RGBA, straight alpha).
        c2w: [N, 3, 4] float32 camera-to-world, OpenGL convention (camera looks down -z, +y up).
        intrinsics: [N, 4] float32 fx, fy, cx, cy in pixels of ``images``.
        distortion: [N, 4] float32 OpenCV k1, k2, p1, p2 (zeros when none).
        names: N image file paths.
        width, height: W and H.
        has_distortion: any distortion coefficient is non-zero (computed; pass ``distortion``
            to :func:`generate_rays` only then).
    """

    images: torch.Tensor
    c2w: torch.Tensor
    intrinsics: torch.Tensor
    distortion: torch.Tensor
    names: list[str]
    width: int
    height: int
    has_distortion: bool = field(init=False)

    def __post_init__(self):
        n = len(self.names)
        expect = {
            "images": (self.images, (n, self.height, self.width, None), torch.uint8),
            "c2w": (self.c2w, (n, 3, 4), torch.float32),
            "intrinsics": (self.intrinsics, (n, 4), torch.float32),
            "distortion": (self.distortion, (n, 4), torch.float32),
        }
        for name, (t, shape, dtype) in expect.items():
            if t.dim() != len(shape) or any(s is not None and s != d for s, d in zip(shape, t.shape)):
                raise ValueError(f"Split.{name} has shape {list(t.shape)}, expected {list(shape)}")
            if t.dtype != dtype:
                raise ValueError(f"Split.{name} must be {dtype}, got {t.dtype}")
        if self.images.shape[-1] not in (3, 4):
            raise ValueError(f"Split.images must have 3 or 4 channels, got {self.images.shape[-1]}")
        self.has_distortion = bool((self.distortion != 0).any())

    def __len__(self) -> int:
        return len(self.names)

    def to(self, device) -> "Split":
        return Split(self.images.to(device), self.c2w.to(device), self.intrinsics.to(device),
                     self.distortion.to(device), list(self.names), self.width, self.height)

    def rays(self, image_index: torch.Tensor, px: torch.Tensor, py: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Rays through pixels (px[b], py[b]) of images image_index[b] (all [B] int, on the
        split's device) -> rays_o [B, 3], rays_d [B, 3] unit; see :func:`generate_rays`."""
        dist = self.distortion[image_index] if self.has_distortion else None
        return generate_rays(self.c2w[image_index], self.intrinsics[image_index], dist, px, py)


@dataclass
class Scene:
    """A loaded scene.

    Attributes:
        train, test: the training and evaluation splits.
        test_is_heldout: the folder had no test split; ``test`` holds every
            ``holdout_every``-th frame, removed from ``train``.
        aabb: [6] float32 xmin, ymin, zmin, xmax, ymax, zmax of the box the field lives in (world).
        occupancy_levels: cascades that box needs: 1 + ceil(log2(aabb_scale)), at least 1.
        near: near distance for rays (world units).
        source: "nerf-synthetic" or "instant-ngp".
        occupancy_aabb: [6] float32, the finest cascade's box: instant-ngp's unit cube in the
            world; cascade k covers it scaled by 2^k about its centre, the last one covers
            ``aabb``. Equal to ``aabb`` when there is one level (defaults to it).
    """

    train: Split
    test: Split
    test_is_heldout: bool
    aabb: torch.Tensor
    occupancy_levels: int
    near: float
    source: str
    occupancy_aabb: torch.Tensor | None = None

    def __post_init__(self):
        if self.occupancy_aabb is None:
            self.occupancy_aabb = self.aabb.clone()


def image_rays(split: Split, index: int) -> tuple[torch.Tensor, torch.Tensor]:
    """All rays of image ``index`` of ``split``, row-major: rays_o, rays_d [H * W, 3] float32."""
    if not 0 <= index < len(split):
        raise ValueError(f"image index {index} out of range for a split of {len(split)} images")
    dev = split.c2w.device
    ys, xs = torch.meshgrid(torch.arange(split.height, device=dev), torch.arange(split.width, device=dev),
                            indexing="ij")
    idx = torch.full((split.height * split.width,), index, device=dev, dtype=torch.long)
    return split.rays(idx, xs.reshape(-1), ys.reshape(-1))


# ---- parsing ----------------------------------------------------------------------------------

@dataclass
class _Frame:
    where: str  # "<json> frame <i>", for messages
    image: Path
    c2w: np.ndarray  # [3, 4] float64
    camera: list[dict]  # camera keys from the json top level, then the frame (overrides)


def _short(v) -> str:
    r = repr(v)
    return r if len(r) <= 40 else r[:37] + "..."


def _number(d: dict, key: str, where: str, positive: bool = False) -> float:
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise DataError(f"{where}: {key} must be a number, got {_short(v)}")
    if not math.isfinite(v):
        raise DataError(f"{where}: {key} is not finite")
    if positive and v <= 0:
        raise DataError(f"{where}: {key} must be positive, got {v}")
    return float(v)


def _read_json(path: Path) -> dict:
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(f"{path}: cannot read ({getattr(e, 'strerror', None) or e})") from None
    try:
        meta = json.loads(text)
    except json.JSONDecodeError as e:
        raise DataError(f"{path}: not valid JSON ({e.msg} at line {e.lineno}, column {e.colno})") from None
    if not isinstance(meta, dict):
        raise DataError(f"{path}: expected a JSON object at the top level, got {type(meta).__name__}")
    return meta


def _natural_key(s: str):
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", s)]


def _matrix(frame: dict, where: str) -> np.ndarray:
    if "transform_matrix" not in frame:
        raise DataError(f"{where}: missing transform_matrix")
    try:
        m = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (TypeError, ValueError):
        m = None
    if m is None or m.shape not in ((4, 4), (3, 4)):
        raise DataError(f"{where}: transform_matrix must be a 4x4 array of numbers")
    if not np.isfinite(m).all():
        raise DataError(f"{where}: transform_matrix has non-finite values")
    if abs(np.linalg.det(m[:3, :3])) < 1e-6:
        raise DataError(f"{where}: transform_matrix is singular")
    return m[:3]


def _image_path(base: Path, file_path, where: str) -> Path:
    if not isinstance(file_path, str) or not file_path:
        raise DataError(f"{where}: file_path must be a non-empty string, got {_short(file_path)}")
    p = Path(file_path.replace("\\", "/"))
    p = p if p.is_absolute() else base / p
    if p.is_file():
        return p
    for ext in IMAGE_EXTENSIONS:
        q = p.with_name(p.name + ext)
        if q.is_file():
            return q
    tried = "" if p.suffix.lower() in IMAGE_EXTENSIONS else " (also tried .png, .jpg, .jpeg)"
    raise DataError(f"{where}: missing image {p}{tried}")


def _camera_keys(d: dict) -> dict:
    return {k: v for k, v in d.items() if k not in ("frames", "file_path", "transform_matrix")}


def _frames(meta: dict, json_path: Path) -> list[_Frame]:
    frames = meta.get("frames")
    if not isinstance(frames, list):
        raise DataError(f"{json_path}: no 'frames' list")
    if not frames:
        raise DataError(f"{json_path}: no frames")
    top = _camera_keys(meta)
    out = []
    for i, frame in enumerate(frames):
        where = f"{json_path} frame {i}"
        if not isinstance(frame, dict):
            raise DataError(f"{where}: expected an object, got {_short(frame)}")
        if "file_path" not in frame:
            raise DataError(f"{where}: missing file_path")
        out.append(_Frame(where, _image_path(json_path.parent, frame["file_path"], where),
                          _matrix(frame, where), [top, _camera_keys(frame)]))
    # Sorted by file name as instant-ngp does, so held-out frames spread along a capture.
    return sorted(out, key=lambda f: _natural_key(str(f.image)))


def _focal(d: dict, width: int, height: int, ref_w: float, ref_h: float, where: str) -> tuple[float, float] | None:
    """(fx, fy) in pixels of the image from one level of keys, or None when it has none.
    Precedence as instant-ngp: x_fov (degrees) > fl_x (pixels at w) > camera_angle_x (radians);
    with one axis given, the other gets the same focal length. A frame that gives any focal
    length replaces the top level's pair, as in instant-ngp."""
    def axis(a: str, res: int, ref: float) -> float | None:
        if f"fl_{a}" in d and f"{a}_fov" not in d:
            return _number(d, f"fl_{a}", where, positive=True) * res / ref
        for key, half_turn in ((f"{a}_fov", 180.0), (f"camera_angle_{a}", math.pi)):
            if key in d:
                angle = _number(d, key, where, positive=True)
                if angle >= half_turn:
                    raise DataError(f"{where}: {key} must be below a half turn, got {angle}")
                return 0.5 * res / math.tan(0.5 * angle * math.pi / half_turn)
        return None

    fx, fy = axis("x", width, ref_w), axis("y", height, ref_h)
    if fx is None and fy is None:
        return None
    return (fx if fx is not None else fy), (fy if fy is not None else fx)


def _intrinsics(frame: _Frame, width: int, height: int) -> tuple[list[float], list[float]]:
    """([fx, fy, cx, cy], [k1, k2, p1, p2]) of a frame whose image is width x height."""
    merged = {**frame.camera[0], **frame.camera[1]}
    for key in _UNSUPPORTED_LENS_KEYS:
        if merged.get(key):
            raise DataError(f"{frame.where}: lens model with '{key}' is not supported (pinhole + k1 k2 p1 p2 only)")
    ref_w = _number(merged, "w", frame.where, positive=True) if "w" in merged else width
    ref_h = _number(merged, "h", frame.where, positive=True) if "h" in merged else height
    focal = _focal(frame.camera[1], width, height, ref_w, ref_h, frame.where)
    if focal is None:
        focal = _focal(frame.camera[0], width, height, ref_w, ref_h, frame.where)
    if focal is None:
        raise DataError(f"{frame.where}: no focal length (needs camera_angle_x, fl_x, x_fov or a y variant)")
    cx = _number(merged, "cx", frame.where) * width / ref_w if "cx" in merged else width / 2
    cy = _number(merged, "cy", frame.where) * height / ref_h if "cy" in merged else height / 2
    dist = [_number(merged, k, frame.where) if k in merged else 0.0 for k in ("k1", "k2", "p1", "p2")]
    return [focal[0], focal[1], cx, cy], dist


def _world_box(meta: dict, json_path: Path) -> tuple[list[float], list[float], int, float]:
    """(field box, finest cascade box, occupancy levels, scale) in the world from instant-ngp's
    scene keys: ngp = world * scale + offset, the field fills [0.5 -+ aabb_scale / 2]^3 and the
    finest cascade [0, 1]^3 of that space."""
    aabb_scale = _number(meta, "aabb_scale", str(json_path), positive=True) if "aabb_scale" in meta else 1.0
    scale = _number(meta, "scale", str(json_path), positive=True) if "scale" in meta else NGP_SCALE
    offset = list(NGP_OFFSET)
    if "offset" in meta:
        raw = meta["offset"]
        raw = raw if isinstance(raw, list) else [raw] * 3
        if len(raw) != 3:
            raise DataError(f"{json_path}: offset must be a number or a list of 3 numbers")
        offset = [_number({"offset": v}, "offset", str(json_path)) for v in raw]
    if "aabb" in meta:  # [[min], [max]] in world units, fitted into the unit cube
        try:
            box = np.asarray(meta["aabb"], dtype=np.float64)
        except (TypeError, ValueError):
            box = None
        if box is None or box.shape != (2, 3) or not np.isfinite(box).all():
            raise DataError(f"{json_path}: aabb must be [[xmin, ymin, zmin], [xmax, ymax, zmax]]")
        scale = 1.0 / max(float(np.abs(box[1] - box[0]).max()), 1e-6)
        offset = list(0.5 - 0.5 * (box[0] + box[1]) * scale)
    def world(ngp_lo: float, ngp_hi: float) -> list[float]:
        return [(ngp_lo - o) / scale for o in offset] + [(ngp_hi - o) / scale for o in offset]

    if aabb_scale > MAX_AABB_SCALE:
        raise DataError(f"{json_path}: aabb_scale {aabb_scale:g} is larger than {MAX_AABB_SCALE} "
                        f"(the occupancy grid has at most 16 cascades)")
    levels = max(1, 1 + math.ceil(math.log2(aabb_scale)))
    return world(0.5 - aabb_scale / 2, 0.5 + aabb_scale / 2), world(0.0, 1.0), levels, scale


# ---- images -------------------------------------------------------------------------------------

def _read_image(path: Path) -> np.ndarray:
    """[H, W, 3 or 4] uint8 from any 8/16-bit grey, grey+alpha, RGB or RGBA file."""
    try:
        a = np.asarray(iio.imread(path, plugin="pillow"))
    except Exception as e:  # imageio/Pillow raise many types for corrupt or unknown files
        reason = "not an image file Pillow can read" if "can not handle" in str(e) else str(e)
        raise DataError(f"{path}: cannot read image ({reason})") from None
    if a.dtype == np.uint16:
        a = ((a.astype(np.uint32) * 255 + 32767) // 65535).astype(np.uint8)
    elif a.dtype == np.bool_:
        a = a.astype(np.uint8) * 255
    elif a.dtype != np.uint8:
        raise DataError(f"{path}: unsupported pixel type {a.dtype} (8 or 16 bit images only)")
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[2] not in (1, 2, 3, 4) or 0 in a.shape:
        raise DataError(f"{path}: unsupported image layout {list(a.shape)}")
    if a.shape[2] <= 2:  # grey (+ alpha)
        a = np.concatenate([np.repeat(a[..., :1], 3, axis=2), a[..., 1:]], axis=2)
    return a


def downscale_image(a: np.ndarray, n: int) -> np.ndarray:
    """Area-average n x n blocks of a uint8 [H, W, C] image (cropped to multiples of n).

    RGBA is averaged premultiplied, so compositing the result on any background equals
    downscaling the composite: rgb = sum(rgb a) / sum(a), alpha = mean(a) (a block with no
    coverage keeps its plain mean colour).
    """
    if n == 1:
        return a
    h, w, c = a.shape[0] // n, a.shape[1] // n, a.shape[2]
    b = a[: h * n, : w * n].reshape(h, n, w, n, c).astype(np.float64)
    if c == 4:
        alpha = b[..., 3:]
        a_sum = alpha.sum(axis=(1, 3))
        rgb_premult = (b[..., :3] * alpha).sum(axis=(1, 3))
        rgb = np.where(a_sum > 0, rgb_premult / np.maximum(a_sum, 1e-12), b[..., :3].mean(axis=(1, 3)))
        out = np.concatenate([rgb, a_sum / (n * n)], axis=-1)
    else:
        out = b.mean(axis=(1, 3))
    return np.clip(np.floor(out + 0.5), 0, 255).astype(np.uint8)


def _load_images(frames: list[_Frame], downscale: int) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """Read, check and downscale every frame's image -> ([N, h, w, C] uint8, original (W, H)s)."""
    def load(frame: _Frame):
        a = _read_image(frame.image)
        if a.shape[0] < downscale or a.shape[1] < downscale:
            raise DataError(f"{frame.image}: image is {a.shape[1]}x{a.shape[0]}, smaller than downscale {downscale}")
        return (a.shape[1], a.shape[0]), downscale_image(a, downscale)

    out, sizes = None, []
    pool = ThreadPoolExecutor(max_workers=min(8, os.cpu_count() or 1))
    try:
        for k, (size, img) in enumerate(pool.map(load, frames)):
            if sizes and size != sizes[0]:
                raise DataError(f"{frames[k].image}: image is {size[0]}x{size[1]} but the first image "
                                f"({frames[0].image.name}) is {sizes[0][0]}x{sizes[0][1]}")
            sizes.append(size)
            if out is None:
                out = np.empty((len(frames), *img.shape), dtype=np.uint8)
            if img.shape[2] > out.shape[3]:  # the first RGBA image after RGB ones: add opaque alpha
                out = np.concatenate([out, np.full(out.shape[:3] + (1,), 255, np.uint8)], axis=3)
            elif img.shape[2] < out.shape[3]:
                img = np.concatenate([img, np.full(img.shape[:2] + (1,), 255, np.uint8)], axis=2)
            out[k] = img
    finally:
        pool.shutdown(wait=True, cancel_futures=True)  # after an error, skip the images not yet read
    return out, sizes


def _split(frames: list[_Frame], images: np.ndarray, sizes: list[tuple[int, int]], downscale: int) -> Split:
    intr, dist = zip(*(_intrinsics(f, w, h) for f, (w, h) in zip(frames, sizes)))
    intrinsics = torch.tensor(intr, dtype=torch.float64) / downscale
    return Split(
        images=torch.from_numpy(images),
        c2w=torch.from_numpy(np.stack([f.c2w for f in frames])).float(),
        intrinsics=intrinsics.float(),
        distortion=torch.tensor(dist, dtype=torch.float32),
        names=[str(f.image) for f in frames],
        width=images.shape[2],
        height=images.shape[1],
    )


def load_scene(path: str | Path, downscale: int = 1, holdout_every: int = 8) -> Scene:
    """Load a NeRF-synthetic folder or an instant-ngp ``transforms.json`` (folder or file).

    Args:
        path: folder with ``transforms_train.json`` (and optionally ``transforms_test.json``),
            folder with ``transforms.json``, or the path of a transforms file.
        downscale: integer factor; images are area-averaged over n x n blocks (cropped to a
            multiple of n) and the intrinsics divided by n.
        holdout_every: without a test split, frames 0, k, 2k, ... (sorted by file name) become
            the test split and leave training.

    Returns:
        The :class:`Scene`; images stay uint8 on the CPU.

    Raises:
        DataError: any problem with the files, in one line naming the file.
    """
    path = Path(path)
    if isinstance(downscale, bool) or not isinstance(downscale, int) or downscale < 1:
        raise DataError(f"downscale must be a positive integer, got {_short(downscale)}")
    if isinstance(holdout_every, bool) or not isinstance(holdout_every, int) or holdout_every < 2:
        raise DataError(f"holdout_every must be an integer of at least 2, got {_short(holdout_every)}")
    if path.is_file():
        train_json, test_json = path, None
    elif path.is_dir():
        if (path / "transforms_train.json").is_file():
            train_json = path / "transforms_train.json"
            test_json = path / "transforms_test.json" if (path / "transforms_test.json").is_file() else None
        elif (path / "transforms.json").is_file():
            train_json, test_json = path / "transforms.json", None
        else:
            raise DataError(f"{path}: no transforms_train.json or transforms.json in this folder")
    else:
        raise DataError(f"{path}: no such file or folder")

    metas = [_read_json(train_json)] + ([_read_json(test_json)] if test_json else [])
    train = _frames(metas[0], train_json)
    if test_json is not None:
        test = _frames(metas[1], test_json)
    else:
        if len(train) < 2:
            raise DataError(f"{train_json}: only 1 frame; at least 2 are needed to hold out test frames")
        test = train[::holdout_every]
        train = [f for k, f in enumerate(train) if k % holdout_every]

    images, sizes = _load_images(train + test, downscale)
    n = len(train)
    is_ngp = train_json.name != "transforms_train.json" or any(k in m for m in metas for k in _NGP_SCENE_KEYS)
    if is_ngp:
        aabb, cascade_box, levels, scale = _world_box(metas[0], train_json)
    else:
        b = NERF_SYNTHETIC_BOUND
        aabb, levels, scale = [-b, -b, -b, b, b, b], 1, 0.5 / b
        cascade_box = aabb
    return Scene(
        train=_split(train, images[:n], sizes[:n], downscale),
        test=_split(test, images[n:], sizes[n:], downscale),
        test_is_heldout=test_json is None,
        aabb=torch.tensor(aabb, dtype=torch.float32),
        occupancy_levels=levels,
        near=round(NEAR_IN_UNIT_CUBE / scale, 6),
        source="instant-ngp" if is_ngp else "nerf-synthetic",
        occupancy_aabb=torch.tensor(cascade_box, dtype=torch.float32),
    )
