"""Checkpoints: everything needed to resume training, evaluate or render, saved atomically.

A checkpoint is a dict saved by ``torch.save``: ``format``, ``scene`` (the scene folder and
downscale), ``train_config`` (the resolved :class:`~ngp_warp.config.TrainConfig` as a dict),
the keys of :meth:`Trainer.state_dict <ngp_warp.trainer.Trainer.state_dict>` and ``rng`` (torch's
CPU generator state).
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import torch

from ngp_warp.atomic import atomic_file
from ngp_warp.config import TrainConfig
from ngp_warp.data import DataError, load_scene
from ngp_warp.field import FieldConfig
from ngp_warp.trainer import Trainer

FORMAT = "ngp-warp-checkpoint-v1"


class CheckpointError(ValueError):
    """A checkpoint that is missing, unreadable or not ours; the message is one line."""


def save_checkpoint(trainer: Trainer, path: Path, scene_path: Path, downscale: int) -> None:
    """Write ``path`` atomically (temporary file, then rename)."""
    state = {
        "format": FORMAT,
        "scene": {"path": str(Path(scene_path).resolve()), "downscale": int(downscale)},
        "train_config": asdict(trainer.config),
        **trainer.state_dict(),
        "rng": torch.get_rng_state(),
    }
    with atomic_file(path) as tmp:
        torch.save(state, tmp)


def read_checkpoint(path: Path) -> dict:
    """The checkpoint dict in ``path`` (tensors on the CPU); CheckpointError if there is none
    or it is not ours."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no checkpoint there (train first: ngp-warp train SCENE --out DIR)")
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # torch raises many kinds for a damaged file
        raise CheckpointError(f"{path}: not a readable checkpoint ({type(e).__name__})") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not an ngp-warp checkpoint")
    return state


def _train_config(path: Path, saved: dict) -> TrainConfig:
    """The checkpoint's settings; CheckpointError for a setting this version does not have or
    accept. Checkpoints from before sub-rays trained one ray per pixel."""
    saved = {"supersample": 1, **saved}
    try:
        config = TrainConfig(**{**saved, "field": FieldConfig(**saved["field"])})
        config.check()
    except TypeError as e:  # a setting this version does not have
        raise CheckpointError(f"{path}: written by another ngp-warp version ({e})") from None
    except ValueError as e:  # a setting this version does not accept
        raise CheckpointError(f"{path}: {e}") from None
    return config


def load_trainer(path: Path, device: str | None = None, scene_path: Path | None = None) -> tuple[Trainer, dict]:
    """Rebuild the trainer saved in ``path`` (its scene is re-read from the recorded folder,
    or ``scene_path``). Returns the trainer and the checkpoint's scene record."""
    state = read_checkpoint(path)
    try:
        record = dict(state["scene"])
        if scene_path is not None:
            record["path"] = str(Path(scene_path).resolve())
        try:
            scene = load_scene(record["path"], downscale=record["downscale"])
        except DataError as e:
            raise CheckpointError(f"{path}: cannot reload its scene: {e}") from None
        trainer = Trainer(scene, _train_config(path, state["train_config"]), device=device)
        trainer.load_state_dict(state)
        torch.set_rng_state(state["rng"])
    except KeyError as e:  # a part this version saves and the file lacks
        raise CheckpointError(f"{path}: written by another ngp-warp version (no {e.args[0]!r} in it)") from None
    return trainer, record
