"""Checkpoints: everything needed to resume training, evaluate or render, saved atomically."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import torch

from ngp_warp.atomic import atomic_file
from ngp_warp.data import DataError, load_scene
from ngp_warp.field import FieldConfig
from ngp_warp.trainer import TrainConfig, Trainer

FORMAT = "ngp-warp-checkpoint-v1"


class CheckpointError(ValueError):
    """A checkpoint that is missing, unreadable or not ours; the message is one line."""


def save_checkpoint(trainer: Trainer, path: Path, scene_path: Path, downscale: int) -> None:
    """Write ``path`` atomically (temporary file, then rename)."""
    averaged = trainer.averaged_weights()  # flush first: the optimizer's state then matches it
    state = {
        "format": FORMAT,
        "scene": {"path": str(Path(scene_path).resolve()), "downscale": int(downscale)},
        "train_config": asdict(trainer.config),
        "field": trainer.field.state_dict(),
        "grid": trainer.grid.state_dict(),
        "optimizer": trainer.optimizer.state_dict(),
        "table_optimizer": None if trainer.table_optimizer is None else trainer.table_optimizer.state_dict(),
        "averaged": averaged,
        "step": trainer.step_count,
        "train_seconds": trainer.train_seconds,
        "n_rays": trainer.n_rays,
        "sample_fraction": trainer._fraction,  # contributing / marched samples, steers the ray count
        "rng": torch.get_rng_state(),
    }
    with atomic_file(path) as tmp:
        torch.save(state, tmp)


def read_checkpoint(path: Path) -> dict:
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


def load_trainer(path: Path, device: str | None = None, scene_path: Path | None = None) -> tuple[Trainer, dict]:
    """Rebuild the trainer saved in ``path`` (its scene is re-read from the recorded folder,
    or ``scene_path``). Returns the trainer and the checkpoint's scene record."""
    state = read_checkpoint(path)
    record = dict(state["scene"])
    if scene_path is not None:
        record["path"] = str(Path(scene_path).resolve())
    try:
        scene = load_scene(record["path"], downscale=record["downscale"])
    except DataError as e:
        raise CheckpointError(f"{path}: cannot reload its scene: {e}") from None
    cfg_dict = {"supersample": 1, **state["train_config"]}  # trained before sub-rays: one ray per pixel
    try:
        cfg = TrainConfig(**{**cfg_dict, "field": FieldConfig(**cfg_dict["field"])})
        cfg.check()
    except TypeError as e:  # a setting this version does not have
        raise CheckpointError(f"{path}: written by another ngp-warp version ({e})") from None
    except ValueError as e:  # a setting this version does not accept
        raise CheckpointError(f"{path}: {e}") from None
    trainer = Trainer(scene, cfg, device=device)
    trainer.field.load_state_dict(state["field"])
    trainer.grid.load_state_dict(state["grid"])
    trainer.optimizer.load_state_dict(state["optimizer"])
    if trainer.table_optimizer is not None:
        trainer.table_optimizer.load_state_dict(state["table_optimizer"])
    if trainer.averaged is not None:  # checkpoints from before weight averaging start it from the weights
        saved = state.get("averaged") or [p.detach() for p in trainer.field.parameters()]
        torch._foreach_copy_(trainer.averaged, [t.to(trainer.device) for t in saved])
    trainer.step_count = state["step"]
    trainer.train_seconds = state["train_seconds"]
    trainer.n_rays = state["n_rays"]
    trainer._fraction = state.get("sample_fraction", 1.0)
    torch.set_rng_state(state["rng"])
    return trainer, record
