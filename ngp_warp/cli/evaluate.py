"""``ngp-warp eval``."""

from __future__ import annotations

import json
from pathlib import Path

from ngp_warp.cli.common import CHECKPOINT, TRAINING_KEYS, print_metrics, resolve_device, writable_dir


def _training_metrics(out: Path) -> dict:
    """What the training command wrote into ``out/metrics.json`` that evaluation does not
    (:data:`TRAINING_KEYS`), so that a new evaluation keeps it; {} without a readable file."""
    try:
        previous = json.loads((out / "metrics.json").read_text())
    except (OSError, ValueError):
        return {}
    return {k: previous[k] for k in TRAINING_KEYS if isinstance(previous, dict) and k in previous}


def cmd_eval(args) -> None:
    from ngp_warp.atomic import remove_stale_partials
    from ngp_warp.training.checkpoint import load_trainer
    from ngp_warp.outputs.evaluate import evaluate, write_metrics
    from ngp_warp.training.run_folder import check_output_names

    check_output_names(Path(args.dir))  # e.g. renders/ that is a file: refused before loading
    trainer, _ = load_trainer(Path(args.dir) / CHECKPOINT, device=resolve_device(args.device), scene_path=args.scene)
    out = writable_dir(Path(args.dir))
    remove_stale_partials(out)  # left by an evaluation that was killed
    kept = _training_metrics(out)
    metrics = evaluate(trainer, out, show_progress=not args.quiet)
    if kept:
        metrics = write_metrics(out, {**metrics, **kept})
    print_metrics(metrics, out, trained=False)
