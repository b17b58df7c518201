"""nerfstudio's trained frame: a camera path made in nerfstudio's viewer on a nerfstudio training
holds poses in the frame that training's dataparser moved the data to (oriented, centred and
scaled; its ``dataparser_transforms.json``), which :func:`from_dataparser_frame` undoes, as
nerfstudio's ``transform_poses_to_original_space`` does, back to the scene file's frame, the
one ngp-warp trains in."""

from __future__ import annotations

import math
from pathlib import Path

import torch

from ngp_warp.data.transforms_json import read_json, transforms_file


def read_dataparser_transform(path: str | Path, scene: str | Path | None = None) -> tuple[torch.Tensor, float]:
    """nerfstudio's ``dataparser_transforms.json`` (written into a nerfstudio training's output
    folder) as the map from the ``scene``'s transforms file's frame to the frame nerfstudio
    trained in: (``transform`` [3, 4] float64, rigid; ``scale``), ``p_ns = scale · (R p + t)``.

    nerfstudio saves the map from the data's original frame: its ``transform`` already holds
    the scene file's ``applied_transform`` A (``ns-process-data`` writes it; a file without it
    beside ``colmap/sparse/0`` takes nerfstudio's old COLMAP default) and its ``scale`` the
    file's ``applied_scale``; both come out here (``transform · A⁻¹``, ``scale / applied_scale``).
    ValueError with one line for anything else."""
    meta = read_json(Path(path))
    try:
        transform = torch.tensor(meta["transform"], dtype=torch.float64)
        scale = float(meta["scale"])
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{path}: not a nerfstudio dataparser_transforms.json ({type(e).__name__}: {e})") from None
    if transform.shape != (3, 4) or not torch.isfinite(transform).all() or not (0 < scale < math.inf):
        raise ValueError(f"{path}: transform must be 3 rows of 4 finite numbers and scale a positive number")
    applied, applied_scale = _applied_transform(scene)
    transform = (_homogeneous(transform) @ torch.linalg.inv(_homogeneous(applied)))[:3]
    rotation = transform[:, :3]
    if orthonormal_error(rotation) > 1e-4 or torch.det(rotation) < 0:
        raise ValueError(f"{path}: transform is not a rotation and a translation")
    return transform, scale / applied_scale


def orthonormal_error(rotation: torch.Tensor) -> torch.Tensor:
    """max |RᵀR − I| of each [..., 3, 3] float64 matrix R → [...]: 0 for a rotation (or a
    reflection), larger for a scaled or sheared one."""
    eye = torch.eye(3, dtype=rotation.dtype)
    return (rotation.transpose(-1, -2) @ rotation - eye).abs().amax((-2, -1))


NERFSTUDIO_COLMAP_APPLIED = [[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0]]


def _homogeneous(m: torch.Tensor) -> torch.Tensor:
    return torch.cat([m, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=m.dtype)])


def _applied_transform(scene: str | Path | None) -> tuple[torch.Tensor, float]:
    """The scene file's ``applied_transform`` [3, 4] float64 and ``applied_scale``, as
    nerfstudio's dataparser reads them (identity and 1 without a scene file)."""
    path = None if scene is None else transforms_file(scene)
    meta = {} if path is None else read_json(path)
    applied = meta.get("applied_transform")
    if applied is None and path is not None and (path.parent / "colmap" / "sparse" / "0").is_dir():
        applied = NERFSTUDIO_COLMAP_APPLIED  # nerfstudio's effective value before the key existed
    try:
        applied = torch.eye(4, dtype=torch.float64)[:3] if applied is None else torch.tensor(applied, dtype=torch.float64)
        applied_scale = float(meta.get("applied_scale", 1.0))
    except (TypeError, ValueError) as e:
        raise ValueError(f"{path}: applied_transform or applied_scale unreadable ({type(e).__name__}: {e})") from None
    if applied.shape != (3, 4) or not torch.isfinite(applied).all() or not (0 < applied_scale < math.inf):
        raise ValueError(f"{path}: applied_transform must be 3 rows of 4 finite numbers and applied_scale positive")
    return applied, applied_scale


def from_dataparser_frame(c2w: torch.Tensor, transform: torch.Tensor, scale: float) -> torch.Tensor:
    """Camera-to-world poses [N, 3, 4] in nerfstudio's trained frame → the data's own frame
    ([N, 3, 4] float64), the inverse of :func:`read_dataparser_transform`'s map (nerfstudio's
    ``transform_poses_to_original_space``, OpenGL axes): ``R_w = Rᵀ R_ns``, ``t_w = Rᵀ (t_ns / scale − t)``."""
    rotation, shift = transform[:, :3], transform[:, 3]
    c2w = c2w.double()
    turned = rotation.T @ c2w[:, :, :3]
    position = (c2w[:, :, 3] / scale - shift) @ rotation  # Rᵀ v for each row v
    return torch.cat([turned, position[:, :, None]], -1)
