"""NeRF-synthetic and instant-ngp ``transforms.json`` files: frames, cameras, lenses, scene box.

* NeRF-synthetic: ``transforms_train.json`` (+ ``transforms_test.json``), ``camera_angle_x``,
  RGBA PNGs named without extension; the field lives in [-1.5, 1.5]^3.
* instant-ngp: ``transforms.json`` (or split files carrying instant-ngp keys) with ``fl_x``,
  ``fl_y``, ``cx``, ``cy``, ``w``, ``h``, ``camera_angle_x/y``, ``x_fov/y_fov``, the lens
  (``camera_model`` OPENCV or OPENCV_FISHEYE, or instant-ngp's ``is_fisheye``; coefficients
  ``k1 k2 k3 k4 p1 p2``), ``aabb_scale``, ``scale``, ``offset``, ``aabb``; every camera key may
  be overridden per frame. instant-ngp maps world p to its unit cube as p * scale + offset
  (default 0.33 and 0.5) and lets the field fill [0.5 - aabb_scale/2, 0.5 + aabb_scale/2]^3
  there; the scene stays in world coordinates (the transform matrices as given).
* ngp-warp's own key ``contraction`` (``"l2"`` or ``"linf"``): the capture is unbounded and the
  field should contract space around ``aabb`` (:func:`contraction_key`).

Frames whose image is missing are skipped, as instant-ngp does, with one warning per file.
instant-ngp's keys that choose frames or change pixels (``n_frames``, sharpness, transparent
white or black) and those read past with a warning: :mod:`ngp_warp.data.ngp_frames`.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ngp_warp.data.data_error import DataError, number, short
from ngp_warp.data.ngp_frames import chosen_frames, natural_key, transparent_colour, warn_ignored

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
NGP_SCALE = 0.33  # instant-ngp's default world -> unit-cube scale (NERF_SCALE)
NGP_OFFSET = (0.5, 0.5, 0.5)
NGP_SCENE_KEYS = ("aabb_scale", "scale", "offset", "aabb", "contraction")
MAX_AABB_SCALE = 2**15  # 16 occupancy cascades
FAR_CAMERA = 1e4  # a camera this many times the median spread from the others is a broken pose
# instant-ngp switches lens on these keys' presence, whatever their values (ftheta_p0 is often 0)
_UNSUPPORTED_LENS_KEYS = ("ftheta_p0", "ftheta_p1", "ftheta_p2", "ftheta_p3", "ftheta_p4", "latlong", "equirectangular")
PERSPECTIVE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")
FISHEYE_MODEL = "OPENCV_FISHEYE"
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")

log = logging.getLogger("ngp_warp.data.loading")


@dataclass
class Frame:
    """One frame: ``c2w`` [3, 4] float64 OpenGL camera-to-world; ``camera`` the camera keys of
    the file's top level, then the frame's (which override them); ``mask`` nerfstudio's
    ``mask_path`` (train on its nonzero pixels) or, without one, instant-ngp's
    ``dynamic_mask_<image stem>.png`` beside the image (``mask_marks_out``: train on its
    black pixels), None without either."""

    where: str  # "<file> frame <i>", for messages
    image: Path
    c2w: np.ndarray
    camera: list[dict]
    mask: Path | None = None
    mask_marks_out: bool = False
    transparent: tuple[int, ...] = ()  # colour values whose pixels are transparent (white_transparent ...)


def transforms_file(scene: str | Path) -> Path | None:
    """A scene's transforms file: itself, or the folder's transforms.json or
    transforms_train.json; None where there is none (a COLMAP model)."""
    scene = Path(scene)
    for path in [scene] if scene.is_file() else [scene / "transforms.json", scene / "transforms_train.json"]:
        if path.is_file():
            return path
    return None


def read_json(path: Path) -> dict:
    """The JSON object in ``path``, or a one-line DataError."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(f"{path}: cannot read ({getattr(e, 'strerror', None) or e})") from None
    try:
        meta = json.loads(text, parse_int=_int_or_float)
    except json.JSONDecodeError as e:
        raise DataError(f"{path}: not valid JSON ({e.msg} at line {e.lineno}, column {e.colno})") from None
    except RecursionError:
        raise DataError(f"{path}: JSON nested too deeply to read") from None
    if not isinstance(meta, dict):
        raise DataError(f"{path}: expected a JSON object at the top level, got {type(meta).__name__}")
    return meta


def _int_or_float(digits: str) -> int | float:
    """A JSON integer; one too long for a float becomes inf, which the finite checks name."""
    return int(digits) if len(digits) <= 18 else float(digits)


def _matrix(value, where: str, key: str = "transform_matrix") -> np.ndarray:
    """[4, 4] (or [3, 4]) finite float64 matrix ``value``."""
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        m = None
    if m is None or m.shape not in ((4, 4), (3, 4)):
        raise DataError(f"{where}: {key} must be a 4x4 array of numbers")
    if not np.isfinite(m).all():
        raise DataError(f"{where}: {key} has non-finite values")
    if m.shape == (4, 4) and np.abs(m[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-6:
        raise DataError(f"{where}: {key}'s bottom row must be [0, 0, 0, 1], got {m[3].tolist()}")
    if abs(np.linalg.det(m[:3, :3])) < 1e-6:
        raise DataError(f"{where}: {key} is singular")
    return m


def _check_rigid(c2w: np.ndarray, where: str) -> None:
    """DataError unless the rotation part of a camera pose is a rotation (orthonormal columns,
    within 1 %): a scaled or sheared one would change the rays' lengths and angles."""
    rotation = c2w[:, :3]
    error = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if error > 0.02:
        norms = ", ".join(f"{n:.4g}" for n in np.linalg.norm(rotation, axis=0))
        raise DataError(f"{where}: transform_matrix is not a rigid camera pose (its rotation columns have "
                        f"lengths {norms} and must be orthonormal)")


def check_pose_set(frames: list[Frame], source) -> None:
    """DataError for camera poses no capture has: every frame at one pose, or a camera more than
    :data:`FAR_CAMERA` times the cameras' median spread from their median (a broken pose)."""
    if len(frames) < 2:
        return
    c2w = np.stack([f.c2w for f in frames])
    if np.ptp(c2w, axis=0).max() <= 1e-9 * max(1.0, float(np.abs(c2w).max())):
        raise DataError(f"{source}: all {len(frames)} frames have the same camera pose (training needs views "
                        f"from different places)")
    distance = np.linalg.norm(c2w[:, :, 3] - np.median(c2w[:, :, 3], axis=0), axis=1)
    spread, far = float(np.median(distance)), int(distance.argmax())
    if spread > 0 and distance[far] > FAR_CAMERA * spread:
        raise DataError(f"{frames[far].where}: its camera is {distance[far]:.3g} from the others' median position, "
                        f"{distance[far] / spread:.3g} times their spread (a broken pose)")


def image_path(base: Path, file_path, where: str) -> Path:
    """The image file of ``file_path`` (extension optional), or the path tried when there is none;
    a DataError when a folder, or a link that leads nowhere, stands where the image would be."""
    if not isinstance(file_path, str) or not file_path:
        raise DataError(f"{where}: file_path must be a non-empty string, got {short(file_path)}")
    p = Path(file_path.replace("\\", "/"))
    p = p if p.is_absolute() else base / p
    for q in [p] + [p.with_name(p.name + ext) for ext in IMAGE_EXTENSIONS]:
        if q.is_file():
            return q
        if q.is_dir() and q.suffix.lower() in IMAGE_EXTENSIONS:
            raise DataError(f"{where}: {q} is a folder, not an image")
        if q.is_symlink() and not q.exists():
            raise DataError(f"{where}: {q} is a link that leads nowhere (a loop or a missing target)")
    return p


def _camera_keys(d: dict) -> dict:
    return {k: v for k, v in d.items() if k not in ("frames", "file_path", "transform_matrix", "transform_matrix_start")}


def read_frames(meta: dict, source: Path, base: Path) -> list[Frame]:
    """The frames of ``meta`` (read from ``source``, image paths relative to ``base``) whose image
    exists, sorted by file name as instant-ngp does (so held-out frames spread along a capture).
    Skipped frames are counted in one warning; none left is a DataError."""
    frames = meta.get("frames")
    if not isinstance(frames, list):
        raise DataError(f"{source}: no 'frames' list")
    if not frames:
        raise DataError(f"{source}: no frames")
    chosen = chosen_frames(meta, frames, source)
    top, out, read, missing = _camera_keys(meta), [], [], []
    transparent = transparent_colour(meta, source)
    for i in chosen:
        frame, where = frames[i], f"{source} frame {i}"
        if not isinstance(frame, dict):
            raise DataError(f"{where}: expected an object, got {short(frame)}")
        pose = "transform_matrix_start" if "transform_matrix_start" in frame else "transform_matrix"
        for key in ("file_path", pose):
            if key not in frame:
                raise DataError(f"{where}: missing {key}")
        c2w = _matrix(frame[pose], where, pose)[:3]
        _check_rigid(c2w, where)
        image = image_path(base, frame["file_path"], where)
        mask = frame.get("mask_path")
        if mask is not None and (not isinstance(mask, str) or not mask):
            raise DataError(f"{where}: mask_path must be a non-empty string, got {short(mask)}")
        if not image.is_file():
            missing.append(image)
            continue
        if mask is not None:
            mask = image_path(base, mask, where)
            if not mask.is_file():
                raise DataError(f"{where}: mask_path {mask}: no such file")
        dynamic = image.with_name(f"dynamic_mask_{image.stem}.png")
        marks_out = mask is None and dynamic.is_file()
        out.append(Frame(where, image, c2w, [top, _camera_keys(frame)], dynamic if marks_out else mask, marks_out,
                         transparent))
        read.append(i)
    if not out:
        raise DataError(f"{source}: none of the {len(chosen)} frames has its image (first missing: {missing[0]})")
    warn_ignored(meta, [(frames[i], f.image) for i, f in zip(read, out)], source)
    if missing:
        log.warning(f"ngp-warp: {source}: skipped {len(missing)} of {len(chosen)} frames whose image is "
                    f"missing (first: {missing[0]})")
    return sorted(out, key=lambda f: natural_key(str(f.image)))


def named_split(meta: dict, frames: list[Frame], source: Path, base: Path) -> tuple[list[Frame], list[Frame]] | None:
    """nerfstudio's split lists: (train, test) of ``frames``, test the frames whose files
    ``test_filenames`` (else ``val_filenames``) names, train those ``train_filenames`` names
    (else every other frame); None when the file has neither test nor val list."""
    key = "test_filenames" if "test_filenames" in meta else "val_filenames" if "val_filenames" in meta else None
    if key is None:
        return None

    def images(name: str) -> set[Path]:
        listed = meta[name]
        if not isinstance(listed, list) or not all(isinstance(x, str) and x for x in listed):
            raise DataError(f"{source}: {name} must be a list of file names")
        return {image_path(base, x, f"{source} {name}").resolve() for x in listed}

    held = images(key)
    resolved = [f.image.resolve() for f in frames]
    test = [f for f, image in zip(frames, resolved) if image in held]
    if not test:
        raise DataError(f"{source}: none of the {len(held)} files {key} names is among the frames read "
                        "(those with an image, within n_frames and the sharpness rule)")
    kept = images("train_filenames") if "train_filenames" in meta else None
    trained = [image in kept if kept is not None else image not in held for image in resolved]
    train = [f for f, t in zip(frames, trained) if t]
    if not train:
        raise DataError(f"{source}: no frame left to train on after {key}")
    both = sum(t and image in held for t, image in zip(trained, resolved))
    if both:
        log.warning(f"ngp-warp: {source}: {both} of the {len(test)} frames {key} names are in train_filenames "
                    "too: they are trained on and scored")
    return train, test


def _focal(d: dict, width: int, height: int, ref_w: float, ref_h: float, where: str) -> tuple[float, float] | None:
    """(fx, fy) in pixels of the image from one level of keys, or None when it has none.
    Precedence as instant-ngp: x_fov (degrees) > fl_x (pixels at w) > camera_angle_x (radians);
    with one axis given, the other gets the same focal length. A frame that gives any focal
    length replaces the top level's pair, as in instant-ngp."""
    def axis(a: str, res: int, ref: float) -> float | None:
        if f"fl_{a}" in d and f"{a}_fov" not in d:
            return number(d, f"fl_{a}", where, positive=True) * res / ref
        for key, half_turn in ((f"{a}_fov", 180.0), (f"camera_angle_{a}", math.pi)):
            if key in d:
                angle = number(d, key, where, positive=True)
                if angle >= half_turn:
                    raise DataError(f"{where}: {key} must be below a half turn, got {angle}")
                return 0.5 * res / math.tan(0.5 * angle * math.pi / half_turn)
        return None

    fx, fy = axis("x", width, ref_w), axis("y", height, ref_h)
    if fx is None and fy is None:
        return None
    return (fx if fx is not None else fy), (fy if fy is not None else fx)


def _lens(merged: dict, where: str) -> tuple[bool, list[float]]:
    """(fisheye, [k1, k2, k3, k4, p1, p2]) of a frame's merged camera keys."""
    for key in _UNSUPPORTED_LENS_KEYS:
        if key in merged:
            raise DataError(f"{where}: lens model with '{key}' is not supported (OPENCV and OPENCV_FISHEYE only)")
    model = merged.get("camera_model", FISHEYE_MODEL if merged.get("is_fisheye") else "OPENCV")
    if model not in PERSPECTIVE_MODELS + (FISHEYE_MODEL,):
        raise DataError(f"{where}: camera_model {short(model)} is not supported "
                        f"({', '.join(PERSPECTIVE_MODELS + (FISHEYE_MODEL,))} are)")
    k = {key: number(merged, key, where) if key in merged else 0.0 for key in DISTORTION_KEYS}
    fisheye = model == FISHEYE_MODEL
    if fisheye and (k["p1"] or k["p2"]):
        raise DataError(f"{where}: {FISHEYE_MODEL} has no tangential terms, but p1/p2 are not zero")
    if not fisheye and k["k4"]:
        raise DataError(f"{where}: k4 is only used by {FISHEYE_MODEL} (camera_model {model} takes k1 k2 k3 p1 p2)")
    return fisheye, [k[key] for key in DISTORTION_KEYS]


def declared_size(frame: Frame) -> tuple[float, float] | None:
    """The frame's ``w`` and ``h`` keys (the image size its pixel keys refer to), if both are given."""
    merged = {**frame.camera[0], **frame.camera[1]}
    if "w" not in merged or "h" not in merged:
        return None
    return number(merged, "w", frame.where, positive=True), number(merged, "h", frame.where, positive=True)


def _check_distortion(dist: list[float], intrinsics: list[float], width: int, height: int, where: str) -> None:
    """DataError for radial coefficients that are no lens over this image: the radial map
    r → r (1 + k1 r² + k2 r⁴ + k3 r⁶ + k4 r⁸) (r normalised, θ for fisheye) must increase up to
    the image corner's distorted radius r_c, and reach it between r_c / 5 and 5 r_c."""
    k1, k2, k3, k4 = dist[:4]
    if not (k1 or k2 or k3 or k4):
        return
    fx, fy, cx, cy = intrinsics
    corner = max(math.hypot((x - cx) / fx, (y - cy) / fy) for x in (0, width) for y in (0, height))
    r = np.linspace(0.0, 5.0 * corner, 4001)[1:]
    r2 = r * r
    mapped = r * (1 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4))))
    reached = np.nonzero(mapped >= corner)[0]
    end = reached[0] if reached.size else len(r)
    increasing = bool(np.all(np.diff(mapped[: end + 1]) > 0))
    if not reached.size or not increasing or r[end] < corner / 5:
        coefficients = ", ".join(f"{n} {v:g}" for n, v in zip(("k1", "k2", "k3", "k4"), dist) if v)
        raise DataError(f"{where}: distortion {coefficients} is not a lens over this {width}x{height} image "
                        f"(its radial map must increase and keep the corner within 5x of its distorted radius)")


def frame_camera(frame: Frame, width: int, height: int) -> tuple[list[float], list[float], bool]:
    """([fx, fy, cx, cy], [k1, k2, k3, k4, p1, p2], fisheye) of a frame whose image is width x height.
    DataError when ``w`` / ``h`` give another aspect ratio than the image's (a different size with
    the same aspect scales the pixel keys to the image)."""
    merged = {**frame.camera[0], **frame.camera[1]}
    fisheye, dist = _lens(merged, frame.where)
    ref_w = number(merged, "w", frame.where, positive=True) if "w" in merged else width
    ref_h = number(merged, "h", frame.where, positive=True) if "h" in merged else height
    if abs((ref_w / ref_h) / (width / height) - 1) > 0.02:
        raise DataError(f"{frame.where}: w x h = {ref_w:g}x{ref_h:g} but the image is {width}x{height} "
                        f"(another aspect ratio)")
    focal = _focal(frame.camera[1], width, height, ref_w, ref_h, frame.where)
    if focal is None:
        focal = _focal(frame.camera[0], width, height, ref_w, ref_h, frame.where)
    if focal is None:
        raise DataError(f"{frame.where}: no focal length (needs camera_angle_x, fl_x, x_fov or a y variant)")
    cx = number(merged, "cx", frame.where) * width / ref_w if "cx" in merged else width / 2
    cy = number(merged, "cy", frame.where) * height / ref_h if "cy" in merged else height / 2
    _check_distortion(dist, [focal[0], focal[1], cx, cy], width, height, frame.where)
    return [focal[0], focal[1], cx, cy], dist, fisheye


def ngp_scale_offset(meta: dict, source: Path) -> tuple[float, list[float]]:
    """(scale, offset) of instant-ngp's map ngp = world * scale + offset from a transforms file's
    ``scale`` and ``offset`` (a number or 3), or its ``aabb`` fitted into the unit cube, else
    instant-ngp's defaults."""
    scale = number(meta, "scale", str(source), positive=True) if "scale" in meta else NGP_SCALE
    offset = list(NGP_OFFSET)
    if "offset" in meta:
        raw = meta["offset"]
        raw = raw if isinstance(raw, list) else [raw] * 3
        if len(raw) != 3:
            raise DataError(f"{source}: offset must be a number or a list of 3 numbers")
        offset = [number({"offset": v}, "offset", str(source)) for v in raw]
    if "aabb" in meta:  # [[min], [max]] in world units, fitted into the unit cube
        try:
            box = np.asarray(meta["aabb"], dtype=np.float64)
        except (TypeError, ValueError):
            box = None
        if box is None or box.shape != (2, 3) or not np.isfinite(box).all():
            raise DataError(f"{source}: aabb must be [[xmin, ymin, zmin], [xmax, ymax, zmax]]")
        scale = 1.0 / max(float(np.abs(box[1] - box[0]).max()), 1e-6)
        offset = list(0.5 - 0.5 * (box[0] + box[1]) * scale)
    return scale, offset


def world_box(meta: dict, source: Path) -> tuple[list[float], list[float], int, float]:
    """(field box, finest cascade box, occupancy levels, scale) in the world from instant-ngp's
    scene keys (:func:`ngp_scale_offset`): the field fills [0.5 -+ aabb_scale / 2]^3 of its unit-cube
    space and the finest cascade [0, 1]^3."""
    aabb_scale = number(meta, "aabb_scale", str(source), positive=True) if "aabb_scale" in meta else 1.0
    scale, offset = ngp_scale_offset(meta, source)

    def world(ngp_lo: float, ngp_hi: float) -> list[float]:
        return [(ngp_lo - o) / scale for o in offset] + [(ngp_hi - o) / scale for o in offset]

    if aabb_scale > MAX_AABB_SCALE:
        raise DataError(f"{source}: aabb_scale {aabb_scale:g} is larger than {MAX_AABB_SCALE} "
                        f"(the occupancy grid has at most 16 cascades)")
    levels = max(1, 1 + math.ceil(math.log2(aabb_scale)))
    return world(0.5 - aabb_scale / 2, 0.5 + aabb_scale / 2), world(0.0, 1.0), levels, scale


def world_from_scene(meta: dict, source: Path) -> np.ndarray:
    """[4, 4] float64 ``world_from_scene`` (ngp-warp's key: the similarity from the file's frame
    back to the capture's, written by :func:`ngp_warp.data.colmap.colmap_to_transforms`), else identity."""
    if "world_from_scene" not in meta:
        return np.eye(4)
    m = _matrix(meta["world_from_scene"], str(source), "world_from_scene")
    if m.shape != (4, 4):  # (its bottom row is checked with every matrix)
        raise DataError(f"{source}: world_from_scene must be a 4x4 matrix")
    return m


CONTRACTIONS = ("l2", "linf")


def contraction_key(meta: dict, source: Path) -> str | None:
    """ngp-warp's ``contraction`` key: ``"l2"`` (mip-NeRF 360) or ``"linf"`` (nerfstudio), the
    scene contraction the capture wants (:mod:`ngp_warp.ops.contraction`); None when absent or null."""
    value = meta.get("contraction")
    if value is not None and value not in CONTRACTIONS:
        raise DataError(f"{source}: contraction must be one of {', '.join(CONTRACTIONS)} or null, got {short(value)}")
    return value
