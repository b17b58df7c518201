"""The training cameras that camera refinement corrected, written back as a transforms file.

``ngp-warp train --set camera_refinement=true`` writes ``OUT/transforms_refined.json``: the
scene's training transforms (``transforms_train.json``, ``transforms.json``, or the instant-ngp
dict of a COLMAP model) with each trained frame's ``transform_matrix`` replaced by its refined
one, every other key kept. Frames held out of training keep theirs. Image paths are made
absolute, so ``ngp-warp train OUT/transforms_refined.json`` trains on the refined poses
wherever the run folder goes. The matrices are in the frame of the file they came from (a COLMAP model's
normalised frame, with its ``world_from_scene`` kept).
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from ngp_warp.atomic import atomic_write_text
from ngp_warp.data.scene_sources import scene_sources
from ngp_warp.data.transforms_json import image_path
from ngp_warp.training.run_folder import REFINED_TRANSFORMS


def refined_transforms(scene_path: str | Path, downscale: int, image_names: list[str],
                       refined_c2w: torch.Tensor) -> dict:
    """The training transforms of the scene at ``scene_path`` with refined poses.

    Args:
        scene_path, downscale: the scene as ``load_scene`` read it.
        image_names: the training split's image paths (``Split.names``), one per refined pose.
        refined_c2w: [len(image_names), 3, 4] float camera-to-world matrices (OpenGL convention),
            e.g. ``CameraRefinement.refined_c2w``.

    Returns:
        The transforms dict; ``refined_from`` names the file (or COLMAP model) it came from.
    """
    if tuple(refined_c2w.shape) != (len(image_names), 3, 4):
        raise ValueError(f"refined_c2w must be [{len(image_names)}, 3, 4], got {tuple(refined_c2w.shape)}")
    meta, source, base = scene_sources(Path(scene_path), downscale)[0][0]
    rows = refined_c2w.detach().double().cpu().tolist()
    refined = {name: matrix + [[0.0, 0.0, 0.0, 1.0]] for name, matrix in zip(image_names, rows)}
    frames = []
    for i, frame in enumerate(meta["frames"]):
        image = image_path(base, frame["file_path"], f"{source} frame {i}")
        moved = {**frame, "file_path": image.absolute().as_posix()}
        if isinstance(frame.get("mask_path"), str) and frame["mask_path"]:
            moved["mask_path"] = image_path(base, frame["mask_path"], f"{source} frame {i}").absolute().as_posix()
        if str(image) in refined:  # the refined pose is the frame's pose (a start pose would be read first)
            moved = {k: v for k, v in moved.items() if k not in ("transform_matrix_start", "transform_matrix_end")}
            moved["transform_matrix"] = refined.pop(str(image))
        frames.append(moved)
    if refined:
        raise ValueError(f"{source}: no frame for {len(refined)} refined image(s), e.g. {next(iter(refined))}")
    return {**meta, "frames": frames, "refined_from": str(source)}


def write_refined_transforms(trainer, scene_path: str | Path, downscale: int, out_dir: str | Path) -> Path:
    """Write :func:`refined_transforms` of ``trainer``'s training split (a Trainer with camera
    refinement) to ``out_dir/transforms_refined.json`` atomically; returns its path."""
    meta = refined_transforms(scene_path, downscale, trainer.train_split.names, trainer.training_c2w())
    path = Path(out_dir) / REFINED_TRANSFORMS
    atomic_write_text(path, json.dumps(meta, indent=2) + "\n")
    return path
