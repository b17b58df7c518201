"""``ngp-warp eval``."""

from __future__ import annotations

from pathlib import Path

from ngp_warp.cli.common import CHECKPOINT, print_metrics, resolve_device, writable_dir

def cmd_eval(args) -> None:
    from ngp_warp.atomic import remove_stale_partials
    from ngp_warp.training.checkpoint import load_trainer
    from ngp_warp.outputs.evaluate import evaluate
    from ngp_warp.training.run_folder import check_output_names

    check_output_names(Path(args.dir))  # e.g. renders/ that is a file: refused before loading
    trainer, _ = load_trainer(Path(args.dir) / CHECKPOINT, device=resolve_device(args.device), scene_path=args.scene)
    out = writable_dir(Path(args.dir))
    remove_stale_partials(out)  # left by an evaluation that was killed
    print_metrics(evaluate(trainer, out, show_progress=not args.quiet), out)
