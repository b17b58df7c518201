"""Generated scenes written as NeRF-synthetic-style folders: the checks, the per-split writer and
the atomic folder that the demo scene (:mod:`ngp_warp.data.scene`) and the unbounded scene
(:mod:`ngp_warp.data.scene_unbounded`) share."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Callable

import imageio.v3 as iio
import numpy as np
import torch

from ngp_warp.atomic import atomic_dir
from ngp_warp.data.data_error import DataError

# render(c2w [V, 3, 4] float32, intrinsics [V, 4] float32) -> [V, H, W, C] float32 in [0, 1]
RenderViews = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def check_positive_ints(**values) -> None:
    """Raise ValueError naming the first value that is not a positive int (bools refused)."""
    for name, v in values.items():
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f"{name} must be a positive int, got {v!r}")


def check_views(c2w, intrinsics, width, height, supersample) -> None:
    """Validate a renderer's cameras: c2w [V, 3, 4] and intrinsics [V, 4] float32 on one device,
    positive int sizes. Raises ValueError with one line."""
    for name, t, shape in (("c2w", c2w, (3, 4)), ("intrinsics", intrinsics, (4,))):
        if not isinstance(t, torch.Tensor) or t.dim() != len(shape) + 1 or tuple(t.shape[1:]) != shape:
            raise ValueError(f"{name} must be a tensor of shape [V, {', '.join(map(str, shape))}]")
        if t.dtype != torch.float32:
            raise ValueError(f"{name} must be float32, got {t.dtype}")
    if intrinsics.shape[0] != c2w.shape[0] or intrinsics.device != c2w.device:
        raise ValueError("c2w and intrinsics must hold the same number of views on the same device")
    check_positive_ints(width=width, height=height, supersample=supersample)


def write_split(folder: Path, split: str, c2w: np.ndarray, width: int, height: int, camera_angle_x: float,
                render: RenderViews, keys: dict) -> None:
    """Render the cameras ``c2w`` ([V, 3, 4] float64, OpenGL axes) of ``split`` with ``render`` and
    write ``folder/split/r_i.png`` and ``folder/transforms_split.json`` (``camera_angle_x``, the
    extra scene ``keys``, the frames)."""
    fx = 0.5 * width / math.tan(0.5 * camera_angle_x)
    c2w32 = torch.from_numpy(c2w).float()  # exactly the float32 matrices load_scene will return
    intrinsics = torch.tensor([[fx, fx, width / 2, height / 2]], dtype=torch.float32).expand(len(c2w), 4)
    pixels = (render(c2w32, intrinsics) * 255.0 + 0.5).clamp(0, 255).to(torch.uint8).numpy()
    (folder / split).mkdir()
    frames = []
    for i, (image, m) in enumerate(zip(pixels, c2w)):
        iio.imwrite(folder / split / f"r_{i}.png", image)
        frames.append({"file_path": f"./{split}/r_{i}",
                       "transform_matrix": np.vstack([m, [0.0, 0.0, 0.0, 1.0]]).tolist()})
    meta = {"camera_angle_x": camera_angle_x, **keys, "frames": frames}
    (folder / f"transforms_{split}.json").write_text(json.dumps(meta, indent=2))


def write_scene_folder(out_dir: str | Path, overwrite: bool, what: str, fill: Callable[[Path], None]) -> Path:
    """Create ``out_dir`` by calling ``fill(tmp)`` on a temporary sibling folder renamed into place
    at the end, so a failure leaves nothing behind (not even parent folders this call created).

    Raises:
        DataError: ``out_dir`` exists (without ``overwrite``) or cannot be written; ``what`` names
        the content in the message.
    """
    out = Path(out_dir)
    if out.exists() and not overwrite:
        raise DataError(f"{out}: already exists (choose another folder or overwrite it)")
    created = [p for p in [out.parent, *out.parent.parents] if not p.exists()]
    done = False
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with atomic_dir(out) as tmp:
            fill(tmp)
        done = True
    except OSError as e:
        raise DataError(f"{out}: cannot write {what} ({e.strerror or e})") from None
    finally:
        for p in [] if done else created:  # innermost first; stops at the first that is not empty
            try:
                p.rmdir()
            except FileNotFoundError:
                continue
            except OSError:
                break
    return out


def write_rendered_scene(out_dir: str | Path, overwrite: bool, what: str, cameras: tuple[np.ndarray, np.ndarray],
                         width: int, height: int, camera_angle_x: float, render: RenderViews, keys: dict,
                         description: dict) -> Path:
    """Write a generated scene as a NeRF-synthetic folder at ``out_dir``: the train and test
    ``cameras`` ([V, 3, 4] float64 each) rendered by ``render`` (:func:`write_split`, with the
    extra scene ``keys``) and ``scene.json`` holding ``description``, through
    :func:`write_scene_folder` (``overwrite`` and ``what`` as there)."""
    def fill(tmp: Path) -> None:
        for split, c2w in zip(("train", "test"), cameras):
            write_split(tmp, split, c2w, width, height, camera_angle_x, render, keys)
        (tmp / "scene.json").write_text(json.dumps(description, indent=2))

    return write_scene_folder(out_dir, overwrite, what, fill)
