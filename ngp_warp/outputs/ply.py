"""Binary little-endian PLY files: coloured point clouds and triangle meshes (no dependency).

The layout written (and the only one :func:`read_ply` accepts)::

    ply
    format binary_little_endian 1.0
    element vertex V
    property float x / y / z
    property uchar red / green / blue        (when colours are given)
    element face F                           (meshes only)
    property list uchar int vertex_indices
    end_header

followed by V packed vertex records and F records of (3, i0, i1, i2).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ngp_warp.atomic import atomic_file

_XYZ = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
_RGB = [("red", "u1"), ("green", "u1"), ("blue", "u1")]
_FACE = np.dtype([("count", "u1"), ("indices", "<i4", (3,))])


def _numpy(t, name: str, dtype, width: int) -> np.ndarray:
    a = t.detach().cpu().numpy() if isinstance(t, torch.Tensor) else np.asarray(t)
    if a.ndim != 2 or a.shape[1] != width:
        raise ValueError(f"{name} must have shape [N, {width}], got {list(a.shape)}")
    return a.astype(dtype, copy=False)


def write_ply(path: str | Path, vertices, colors=None, faces=None) -> Path:
    """Write a point cloud (``faces`` None) or a triangle mesh, atomically.

    Args:
        path: file to write (its folder must exist).
        vertices: [V, 3] float positions (tensor or array; written as float32).
        colors: [V, 3] uint8 RGB per vertex, or None.
        faces: [F, 3] integer vertex indices (written as int32), or None for points only.

    Returns:
        ``path`` as a Path.
    """
    xyz = _numpy(vertices, "vertices", np.float32, 3)
    fields = _XYZ + (_RGB if colors is not None else [])
    records = np.empty(xyz.shape[0], dtype=np.dtype(fields))
    records["x"], records["y"], records["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if colors is not None:
        rgb = _numpy(colors, "colors", np.uint8, 3)
        if rgb.shape[0] != xyz.shape[0]:
            raise ValueError(f"colors has {rgb.shape[0]} rows for {xyz.shape[0]} vertices")
        records["red"], records["green"], records["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {xyz.shape[0]}"]
    header += [f"property float {n}" for n, _ in _XYZ]
    header += [f"property uchar {n}" for n, _ in _RGB] if colors is not None else []
    face_records = None
    if faces is not None:
        tri = _numpy(faces, "faces", np.int64, 3)
        if tri.size and (tri.min() < 0 or tri.max() >= xyz.shape[0]):
            raise ValueError(f"faces index vertices outside [0, {xyz.shape[0]})")
        face_records = np.empty(tri.shape[0], dtype=_FACE)
        face_records["count"] = 3
        face_records["indices"] = tri
        header += [f"element face {tri.shape[0]}", "property list uchar int vertex_indices"]
    header.append("end_header")
    path = Path(path)
    with atomic_file(path) as tmp, open(tmp, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(records.tobytes())
        if face_records is not None:
            f.write(face_records.tobytes())
    return path


def read_ply(path: str | Path) -> dict:
    """Read a file in the layout :func:`write_ply` writes.

    Returns:
        dict with ``vertices`` [V, 3] float32, ``colors`` [V, 3] uint8 or None and ``faces``
        [F, 3] int32 or None (numpy arrays).

    Raises:
        ValueError: the file is not such a PLY file.
    """
    data = Path(path).read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise ValueError(f"{path}: not a PLY file")
    lines = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise ValueError(f"{path}: only binary little-endian PLY files are read")
    counts = {ln.split()[1]: int(ln.split()[2]) for ln in lines if ln.startswith("element ")}
    has_rgb = "property uchar red" in lines
    vertex_dtype = np.dtype(_XYZ + (_RGB if has_rgb else []))
    n_vertices, n_faces = counts.get("vertex", 0), counts.get("face", 0)
    body = data[end + len(b"end_header\n"):]
    if len(body) != n_vertices * vertex_dtype.itemsize + n_faces * _FACE.itemsize:
        raise ValueError(f"{path}: size does not match its header")
    records = np.frombuffer(body, dtype=vertex_dtype, count=n_vertices)
    vertices = np.stack([records["x"], records["y"], records["z"]], -1)
    colors = np.stack([records["red"], records["green"], records["blue"]], -1) if has_rgb else None
    faces = None
    if "face" in counts:
        face_records = np.frombuffer(body, dtype=_FACE, count=n_faces, offset=n_vertices * vertex_dtype.itemsize)
        if (face_records["count"] != 3).any():
            raise ValueError(f"{path}: only triangle faces are read")
        faces = face_records["indices"].astype(np.int32)
    return {"vertices": vertices, "colors": colors, "faces": faces}
