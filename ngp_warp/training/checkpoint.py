"""Checkpoints: everything needed to resume training, evaluate or render, saved atomically.

A checkpoint is a dict saved by ``torch.save``: ``format``, ``scene`` (the scene folder,
downscale and :func:`scene_fingerprint`), ``train_config`` (the resolved :class:`~ngp_warp.training.config.TrainConfig` as a dict),
the keys of :meth:`Trainer.state_dict <ngp_warp.training.trainer.Trainer.state_dict>` and ``rng`` (torch's
CPU generator state).
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict
from pathlib import Path

import numpy as np

import torch

from ngp_warp.atomic import atomic_file
from ngp_warp.training.config import TrainConfig
from ngp_warp.data.data_error import short
from ngp_warp.data.loading import DataError, Scene, load_scene
from ngp_warp.ops.field import FieldConfig
from ngp_warp.training.trainer import Trainer

FORMAT = "ngp-warp-checkpoint-v1"


class CheckpointError(ValueError):
    """A checkpoint that is missing, unreadable or not ours; the message is one line."""


class NonFiniteWeights(CheckpointError):
    """The weights to save hold NaN or infinity (training diverged); nothing was written."""


def scene_fingerprint(scene: Scene) -> dict:
    """What identifies a scene's training split wherever its folder lies: ``views``, ``width``,
    ``height`` and ``digest`` (SHA-1 of the image file names and the camera poses)."""
    split = scene.train
    digest = hashlib.sha1()
    for name in split.names:
        digest.update(Path(name).name.encode() + b"\0")
    digest.update(np.round(split.c2w.double().cpu().numpy(), 5).tobytes())
    return {"views": len(split.names), "width": split.width, "height": split.height, "digest": digest.hexdigest()}


def _check_finite(state: dict, path: Path) -> None:
    floats = [t for t in state["field"].values() if t.is_floating_point()]
    if not bool(torch.stack([torch.isfinite(t).all() for t in floats]).all()):  # one sync
        raise NonFiniteWeights(f"the weights at step {state['step']} are not finite (training diverged); "
                               f"not saved, {path} keeps the last good checkpoint, if any")


def save_checkpoint(trainer: Trainer, path: Path, scene_path: Path, downscale: int,
                    before_write: Callable[[], None] | None = None,
                    writer: ThreadPoolExecutor | None = None) -> Future | None:
    """Write ``path`` atomically (temporary file, then rename); :class:`NonFiniteWeights`,
    writing nothing, when the field's weights hold NaN or infinity. ``before_write`` is called
    once the weights are known good, before anything is written. With ``writer`` the record is
    copied here (on its device) and brought to the host and written on that thread, while the
    caller goes on: the returned future's ``result()`` waits for the file (and raises what
    failed)."""
    state = {
        "format": FORMAT,
        "scene": {"path": str(Path(scene_path).resolve()), "downscale": int(downscale),
                  **scene_fingerprint(trainer.scene)},
        "train_config": asdict(trainer.config),
        **trainer.state_dict(),
        "rng": torch.get_rng_state(),
    }
    _check_finite(state, Path(path))
    if before_write is not None:
        before_write()
    if writer is None:
        _write(state, Path(path))
        return None
    snapshot = _copied(state, lambda t: t.detach().clone())  # on the device: a copy in a fraction of a ms
    device = next(trainer.field.parameters()).device  # a CUDA tensor's device names its index
    ready = torch.cuda.current_stream(device).record_event() if device.type == "cuda" else None
    return writer.submit(_write_snapshot, [snapshot], device, ready, Path(path))


def _write(state: dict, path: Path) -> None:
    with atomic_file(path) as tmp:
        torch.save(state, tmp)


def _write_snapshot(held: list[dict], device: torch.device, ready: torch.cuda.Event | None, path: Path) -> None:
    """Write the copy of the state in ``held`` (a one-item list, emptied here: nothing else
    holds the copy). On CUDA (``ready``: an event after the copy, on ``device``) it comes to the
    host first on a stream of this thread's own, while the caller's stream goes on (lego's
    state takes 0.1–0.2 s to reach the host on an H200), and its device memory is freed then."""
    snapshot = held.pop()
    if ready is not None:
        stream = torch.cuda.Stream(device)
        with torch.cuda.stream(stream):
            stream.wait_event(ready)
            snapshot = _copied(snapshot, lambda t: t.to("cpu"))  # waits for each copy
    _write(snapshot, path)


def _copied(record, copy: Callable[[torch.Tensor], torch.Tensor]):
    """``record`` (dicts, lists and tuples of tensors and other values) with ``copy`` of each
    tensor in place of it."""
    if isinstance(record, torch.Tensor):
        return copy(record)
    if isinstance(record, dict):
        return {k: _copied(v, copy) for k, v in record.items()}
    if isinstance(record, (list, tuple)):
        return type(record)(_copied(v, copy) for v in record)
    return record


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
    _check_records(state, path)
    return state


def _check_records(state: dict, path: Path) -> None:
    """CheckpointError when a record a checkpoint holds has the wrong type or value (a damaged or
    hand-edited file); records it lacks are left to the reader (another version's file)."""
    def wrong(what: str, value) -> CheckpointError:
        return CheckpointError(f"{path}: its {what} is {short(value)}, which no ngp-warp writes (a damaged "
                               f"or hand-edited checkpoint)")

    for key in ("scene", "train_config"):
        if key in state and not isinstance(state[key], dict):
            raise wrong(f"{key!r} record", state[key])
    scene, config = state.get("scene", {}), state.get("train_config", {})
    if "path" in scene and not isinstance(scene["path"], str):
        raise wrong("scene path", scene["path"])
    if "downscale" in scene and (type(scene["downscale"]) is not int or scene["downscale"] < 1):
        raise wrong("downscale", scene["downscale"])
    if "field" in config and not isinstance(config["field"], dict):
        raise wrong("field settings", config["field"])
    if "step" in state and (type(state["step"]) is not int or state["step"] < 0):
        raise wrong("step", state["step"])
    seconds = state.get("train_seconds", 0.0)
    if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) or not 0 <= seconds < math.inf:
        raise wrong("training time", seconds)


def _train_config(path: Path, saved: dict, scene_near: float) -> TrainConfig:
    """The checkpoint's settings; CheckpointError for a setting this version does not have or
    accept. Checkpoints without sub-rays trained one ray per pixel, those without
    ``distortion_spacing`` took the distortion loss in world distances, and those without
    ``field.environment`` had no learned environment, those without ``aabb_scale`` the box of
    the scene's files, those without ``near`` the scene's own near (``scene_near``), those
    without the start's settings a 100-step warm-up, an unopened grid and every point's density."""
    saved = {"supersample": 1, "distortion_spacing": "world", "aabb_scale": None, "near": scene_near,
             "lr_warmup": 100, "occupancy_open_steps": 0, "grid_seen_only": False, **saved}
    try:
        config = TrainConfig(**{**saved, "field": FieldConfig(**{"environment": False, **saved["field"]})})
        config.check()
    except TypeError as e:  # a setting this version does not have
        raise CheckpointError(f"{path}: written by another ngp-warp version ({e})") from None
    except ValueError as e:  # a setting this version does not accept
        raise CheckpointError(f"{path}: {e}") from None
    return config


def _check_same_scene(path: Path, record: dict, scene: Scene) -> None:
    """CheckpointError when ``scene`` is not the one the checkpoint trained on (checkpoints
    from before fingerprints are not checked)."""
    if "digest" not in record:
        return
    mine = scene_fingerprint(scene)
    if mine != {key: record[key] for key in mine}:
        raise CheckpointError(
            f"{record['path']} is not the scene {path} was trained on ({mine['views']} training views "
            f"{mine['width']}x{mine['height']} there, {record['views']} views {record['width']}x{record['height']} "
            f"in the checkpoint, or other cameras)")


def _restore(trainer: Trainer, state: dict, path: Path) -> None:
    try:
        trainer.load_state_dict(state)
        torch.set_rng_state(state["rng"])
    except (RuntimeError, TypeError, ValueError, AttributeError, IndexError) as e:
        reason = " ".join(str(e).split())[:160]
        raise CheckpointError(f"{path}: its saved tensors do not fit its settings ({reason})") from None


def _check_same_box(trainer: Trainer, state: dict, path: Path) -> None:
    """The contraction's inner box the settings rebuild from the scene must be the one the run
    trained in: the step length and the field's initial density follow from it, and only the box
    itself is restored from the file."""
    saved = state["grid"].get("inner_aabb")
    if saved is None:
        return
    built = trainer.grid.inner_aabb_host
    if not torch.allclose(saved.double().cpu(), torch.tensor(built, dtype=torch.float64), rtol=1e-5, atol=1e-6):
        raise CheckpointError(f"{path}: its scene gives another contraction box than the run trained in "
                              f"({[round(v, 4) for v in built]} against {[round(v, 4) for v in saved.tolist()]})")


def load_trainer(path: Path, device: str | None = None, scene_path: Path | None = None) -> tuple[Trainer, dict]:
    """Rebuild the trainer saved in ``path`` (its scene is re-read from the recorded folder,
    or ``scene_path``, which must hold the same views and cameras). Returns the trainer and the
    checkpoint's scene record; CheckpointError for a checkpoint that does not fit."""
    state = read_checkpoint(path)
    try:
        record = dict(state["scene"])
        if scene_path is not None:
            record["path"] = str(Path(scene_path).resolve())
        try:
            scene = load_scene(record["path"], downscale=record["downscale"])
        except DataError as e:
            raise CheckpointError(f"{path}: cannot reload its scene: {e}") from None
        _check_same_scene(path, record, scene)
        trainer = Trainer(scene, _train_config(path, state["train_config"], scene.near), device=device)
        _check_same_box(trainer, state, path)
        _restore(trainer, state, path)
    except KeyError as e:  # a part this version saves and the file lacks
        raise CheckpointError(f"{path}: written by another ngp-warp version (no {e.args[0]!r} in it)") from None
    return trainer, record
