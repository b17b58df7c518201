"""COLMAP sparse models (``cameras``, ``images``, ``points3D`` as .bin or .txt) read with numpy
and struct, and turned into instant-ngp ``transforms.json`` dicts.

Files (little-endian; COLMAP's ``reconstruction_io``):

* ``cameras.bin``: u64 n, then n x (i32 camera_id, i32 model_id, u64 width, u64 height,
  f64 params[P]) with P fixed by the model; ``cameras.txt``: ``ID MODEL W H PARAMS...``.
* ``images.bin``: u64 n, then n x (i32 image_id, f64 qw qx qy qz, f64 tx ty tz, i32 camera_id,
  name NUL-terminated, u64 m, m x (f64 x, f64 y, i64 point3D_id)); ``images.txt``: two lines per
  image, ``ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` then its 2-D points (possibly empty).
* ``points3D.bin``: u64 n, then n x (u64 id, f64 x y z, u8 r g b, f64 error, u64 t,
  t x (i32 image_id, i32 point2D_idx)); ``points3D.txt``: ``ID X Y Z R G B ERROR TRACK...``.

Poses are world-to-camera, x_cam = R(q) x_world + t, camera axes OpenCV's (x right, y down,
z forward); pixel centres sit at integer + 1/2, as in the trainer.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ngp_warp.data.data_error import DataError
from ngp_warp.data.scene_normalisation import normalise_scene

__all__ = ["ColmapCamera", "ColmapImage", "ColmapModel", "read_colmap_model", "colmap_to_transforms",
           "camera_to_world", "SUPPORTED_MODELS"]

# model id -> (name, parameter count), COLMAP's table
MODELS = {0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
          4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
          8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
          11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16)}
_PARAM_COUNT = dict(MODELS.values())
# the models the trainer's lenses cover, and what their parameters are called
SUPPORTED_MODELS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "OPENCV_FISHEYE": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
}


@dataclass
class ColmapCamera:
    """One COLMAP camera: ``params`` [P] float64 in COLMAP's order for ``model``."""

    camera_id: int
    model: str
    width: int
    height: int
    params: np.ndarray


@dataclass
class ColmapImage:
    """One registered image: ``qvec`` [4] float64 (w, x, y, z) and ``tvec`` [3] float64, world-to-camera."""

    image_id: int
    name: str
    qvec: np.ndarray
    tvec: np.ndarray
    camera_id: int


@dataclass
class ColmapModel:
    """A sparse model: cameras by id, images sorted by name, points ``xyz`` [P, 3] float64 and
    ``rgb`` [P, 3] uint8; ``sparse_dir`` the folder it was read from (for messages)."""

    cameras: dict[int, ColmapCamera]
    images: list[ColmapImage]
    points_xyz: np.ndarray
    points_rgb: np.ndarray
    sparse_dir: Path | None = None


# ---- binary --------------------------------------------------------------------------------

class _Bytes:
    """A cursor over a file's bytes; reading past the end is a one-line DataError."""

    def __init__(self, path: Path):
        self.path, self.data, self.at = path, _read_bytes(path), 0

    def take(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        if self.at + size > len(self.data):
            raise DataError(f"{self.path}: truncated file (ends inside {what})")
        out = struct.unpack_from("<" + fmt, self.data, self.at)
        self.at += size
        return out

    def skip(self, size: int, what: str) -> None:
        if self.at + size > len(self.data):
            raise DataError(f"{self.path}: truncated file (ends inside {what})")
        self.at += size

    def name(self, what: str) -> str:
        end = self.data.find(b"\0", self.at)
        if end < 0:
            raise DataError(f"{self.path}: truncated file (ends inside {what})")
        raw, self.at = self.data[self.at:end], end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise DataError(f"{self.path}: {what} has a name that is not UTF-8") from None

    def finish(self) -> None:
        if self.at != len(self.data):
            raise DataError(f"{self.path}: {len(self.data) - self.at} unexpected bytes after the last record")


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as e:
        raise DataError(f"{path}: cannot read ({e.strerror or e})") from None


def _cameras_bin(path: Path) -> list[ColmapCamera]:
    f, out = _Bytes(path), []
    for i in range(f.take("Q", "the camera count")[0]):
        camera_id, model_id, width, height = f.take("iiQQ", f"camera {i}")
        if model_id not in MODELS:
            raise DataError(f"{path}: camera {camera_id} has unknown camera model id {model_id}")
        name, count = MODELS[model_id]
        params = np.array(f.take("d" * count, f"camera {camera_id}"), dtype=np.float64)
        out.append(ColmapCamera(camera_id, name, width, height, params))
    f.finish()
    return out


def _images_bin(path: Path) -> list[ColmapImage]:
    f, out = _Bytes(path), []
    for i in range(f.take("Q", "the image count")[0]):
        values = f.take("i7di", f"image {i}")
        name = f.name(f"image {values[0]}")
        f.skip(24 * f.take("Q", f"image {values[0]}")[0], f"the 2-D points of image {values[0]}")
        out.append(ColmapImage(values[0], name, np.array(values[1:5]), np.array(values[5:8]), values[8]))
    f.finish()
    return out


def _points_bin(path: Path) -> tuple[np.ndarray, np.ndarray]:
    f = _Bytes(path)
    n = f.take("Q", "the point count")[0]
    xyz, rgb = np.empty((n, 3)), np.empty((n, 3), np.uint8)
    for i in range(n):
        values = f.take("Q3d3BdQ", f"point {i}")
        xyz[i], rgb[i] = values[1:4], values[4:7]
        f.skip(8 * values[8], f"the track of point {values[0]}")
    f.finish()
    return xyz, rgb


# ---- text ----------------------------------------------------------------------------------

def _lines(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, fields) of every line but comments; blank lines kept (images.txt needs them)."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(f"{path}: cannot read ({getattr(e, 'strerror', None) or e})") from None
    return [(k + 1, line.split()) for k, line in enumerate(text.splitlines()) if not line.startswith("#")]


def _parse(path: Path, line: int, fields: list[str], types: str):
    """Fields converted by ``types`` (i int, f float, s str), or a DataError naming the line."""
    if len(fields) < len(types):
        raise DataError(f"{path}: line {line} has {len(fields)} fields, expected at least {len(types)}")
    try:
        return [{"i": int, "f": float, "s": str}[t](v) for t, v in zip(types, fields)]
    except ValueError:
        raise DataError(f"{path}: line {line} is malformed ({' '.join(fields)[:60]})") from None


def _cameras_txt(path: Path) -> list[ColmapCamera]:
    out = []
    for line, fields in _lines(path):
        if not fields:
            continue
        camera_id, model, width, height = _parse(path, line, fields, "isii")
        if model not in _PARAM_COUNT:
            raise DataError(f"{path}: line {line}: unknown camera model {model!r}")
        count = _PARAM_COUNT[model]
        if len(fields) != 4 + count:
            raise DataError(f"{path}: line {line}: camera model {model} takes {count} parameters, "
                            f"got {len(fields) - 4}")
        params = np.array(_parse(path, line, fields[4:], "f" * count), dtype=np.float64)
        out.append(ColmapCamera(camera_id, model, width, height, params))
    return out


def _image_like(fields: list[str]) -> bool:
    """Whether a line's fields read as an image line (IMAGE_ID, 7 numbers, CAMERA_ID, NAME), not
    as its POINTS2D line (numbers in triples)."""
    def number(text: str) -> bool:
        try:
            float(text)
        except ValueError:
            return False
        return True
    points = len(fields) % 3 == 0 and all(number(f) for f in fields)
    return len(fields) >= 10 and not points and fields[0].isdigit() and fields[8].isdigit()


def _images_txt(path: Path) -> list[ColmapImage]:
    """The images of an images.txt: two lines each (the pose, then the 2-D points, perhaps empty),
    or one line each in files written by hand without the points lines."""
    lines, out = _lines(path), []
    while lines and not lines[-1][1]:
        lines.pop()  # blank lines at the end
    second = [fields for _, fields in lines[1::2] if fields]
    one_line_each = bool(second) and all(_image_like(fields) for fields in second)
    for line, fields in [entry for entry in lines if entry[1]] if one_line_each else lines[0::2]:
        if len(fields) > 10:  # a name with spaces
            fields = fields[:9] + [" ".join(fields[9:])]
        v = _parse(path, line, fields, "ifffffffis")
        out.append(ColmapImage(v[0], v[9], np.array(v[1:5]), np.array(v[5:8]), v[8]))
    return out


def _points_txt(path: Path) -> tuple[np.ndarray, np.ndarray]:
    rows = [_parse(path, line, fields, "iffffff") for line, fields in _lines(path) if fields]
    values = np.array([r[1:] for r in rows], dtype=np.float64).reshape(-1, 6)
    if ((values[:, 3:] < 0) | (values[:, 3:] > 255)).any():
        raise DataError(f"{path}: a point colour is outside 0..255")
    return values[:, :3].copy(), values[:, 3:].astype(np.uint8)


# ---- the model -----------------------------------------------------------------------------

def read_colmap_model(sparse_dir: Path) -> ColmapModel:
    """Read ``cameras``, ``images`` and ``points3D`` (all .bin, else all .txt) from ``sparse_dir``.

    Returns:
        The :class:`ColmapModel`, images sorted by name, quaternions normalised.

    Raises:
        DataError: a missing or unreadable file, a truncated or malformed record, an unknown
            camera model, an image whose camera is not in the model, non-finite numbers.
    """
    sparse_dir = Path(sparse_dir)
    ext = ".bin" if (sparse_dir / "cameras.bin").is_file() else ".txt"
    paths = [sparse_dir / f"{name}{ext}" for name in ("cameras", "images", "points3D")]
    for p in paths:
        if not p.is_file():
            raise DataError(f"{p}: missing (a COLMAP model needs cameras, images and points3D, all .bin or all .txt)")
    if ext == ".bin":
        cameras, images, (xyz, rgb) = _cameras_bin(paths[0]), _images_bin(paths[1]), _points_bin(paths[2])
    else:
        cameras, images, (xyz, rgb) = _cameras_txt(paths[0]), _images_txt(paths[1]), _points_txt(paths[2])
    by_id = {c.camera_id: c for c in cameras}
    for c in cameras:
        if c.width <= 0 or c.height <= 0 or not np.isfinite(c.params).all():
            raise DataError(f"{paths[0]}: camera {c.camera_id} has a bad size or non-finite parameters")
    for im in images:
        norm = float(np.linalg.norm(im.qvec))
        if not (np.isfinite(im.tvec).all() and np.isfinite(norm) and norm > 1e-12):
            raise DataError(f"{paths[1]}: image {im.image_id} ({im.name}) has a bad pose")
        if im.camera_id not in by_id:
            raise DataError(f"{paths[1]}: image {im.image_id} ({im.name}) uses camera {im.camera_id}, "
                            f"which {paths[0].name} does not have")
        im.qvec = im.qvec / norm
    if not images:
        raise DataError(f"{paths[1]}: the model has no registered images")
    if not np.isfinite(xyz).all():
        raise DataError(f"{paths[2]}: non-finite point coordinates")
    return ColmapModel(by_id, sorted(images, key=lambda im: im.name), xyz, rgb, sparse_dir)


def camera_to_world(image: ColmapImage) -> np.ndarray:
    """[4, 4] float64 camera-to-world of ``image`` in the OpenGL convention (camera looks down
    -z, +y up): C = -R^T t, c2w = [R^T diag(1, -1, -1) | C]."""
    w, x, y, z = image.qvec
    rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    c2w = np.eye(4)
    c2w[:3, :3] = rot.T * np.array([1.0, -1.0, -1.0])
    c2w[:3, 3] = -rot.T @ image.tvec
    return c2w


def camera_keys(camera: ColmapCamera, where: str = "COLMAP model") -> dict:
    """instant-ngp camera keys of a COLMAP camera: ``fl_x fl_y cx cy w h``, ``camera_model``
    (OPENCV or OPENCV_FISHEYE, the latter with instant-ngp's ``is_fisheye``) and the distortion
    coefficients its model has."""
    if camera.model not in SUPPORTED_MODELS:
        raise DataError(f"{where}: camera {camera.camera_id}: camera model {camera.model} is not supported "
                        f"({', '.join(SUPPORTED_MODELS)} are)")
    v = dict(zip(SUPPORTED_MODELS[camera.model], camera.params.tolist()))
    keys = {"camera_model": "OPENCV_FISHEYE" if camera.model == "OPENCV_FISHEYE" else "OPENCV",
            "fl_x": v.get("fx", v.get("f")), "fl_y": v.get("fy", v.get("f")), "cx": v["cx"], "cy": v["cy"],
            "w": camera.width, "h": camera.height}
    keys.update({k: v[k] for k in ("k1", "k2", "k3", "k4", "p1", "p2") if k in v})
    if camera.model == "OPENCV_FISHEYE":
        keys["is_fisheye"] = True
    return keys


def colmap_to_transforms(model: ColmapModel, image_dir_rel: str = "images", aabb_scale: int | None = None) -> dict:
    """An instant-ngp ``transforms.json`` dict of ``model``, normalised (see
    :func:`ngp_warp.data.scene_normalisation.normalise_scene`) so that instant-ngp's box holds it.

    Args:
        model: a model from :func:`read_colmap_model`.
        image_dir_rel: the image folder relative to where the json will live; frames get
            ``file_path`` = ``image_dir_rel/name``.
        aabb_scale: the field's box in instant-ngp unit cubes (a power of two); None picks the
            smallest that holds the cameras and 99% of the sparse points.

    Returns:
        Camera keys (:func:`camera_keys`) at the top level when every image shares them, else per
        frame; ``aabb_scale``; ``world_from_scene`` ([4, 4] list: COLMAP world = M @ scene point,
        an ngp-warp key instant-ngp ignores); ``frames`` with ``file_path`` and the OpenGL
        ``transform_matrix`` in the normalised frame.
    """
    c2w = np.stack([camera_to_world(im) for im in model.images])
    scene_from_world, world_from_scene, box = normalise_scene(c2w, model.points_xyz, aabb_scale)
    rotation = scene_from_world[:3, :3] / np.cbrt(np.linalg.det(scene_from_world[:3, :3]))
    cams = {cid: camera_keys(c, str(model.sparse_dir or "COLMAP model")) for cid, c in model.cameras.items()
            if any(im.camera_id == cid for im in model.images)}
    shared = len({tuple(sorted(k.items())) for k in cams.values()}) == 1
    meta = dict(next(iter(cams.values()))) if shared else {}
    meta.update(aabb_scale=box, world_from_scene=world_from_scene.tolist(), frames=[])
    for im, m in zip(model.images, c2w):
        pose = np.eye(4)
        pose[:3, :3] = rotation @ m[:3, :3]
        pose[:3, 3] = (scene_from_world @ m[:, 3])[:3]
        frame = {"file_path": f"{image_dir_rel.rstrip('/')}/{im.name}", "transform_matrix": pose.tolist()}
        meta["frames"].append(frame if shared else {**frame, **cams[im.camera_id]})
    return meta
