"""Where an evaluation's time goes: the test views of a trained run, phase by phase.

    python benchmarks/profile_eval.py RUN_FOLDER [--device cuda] [--views 200]

Loads the run's checkpoint and times, over its first ``--views`` test views (every phase adds to
the one above it; the device is synchronised at the end of each pass, not per view):

- ``render``: the renders alone (and the ground truth composited, the appearance fit included);
- ``+ PSNR``: and each view's PSNR read on the host;
- ``+ SSIM``: and SSIM;
- ``+ images to host``: and the render and its depth map as uint8 on the host;
- ``evaluate()``: the whole evaluation as ``ngp-warp eval`` runs it (files written to a temporary
  folder), over every test view, scaled to ``--views``.

With appearance codes (captures) it also times the evaluation's code path per view: the code
fit on the left half, the render with the fitted code that also colours the same samples with
the nearest and the mean code (``other_codes``), and beside it the three renders alone.

On CUDA it then prints the device-busy time per view of 10 renders (torch.profiler), so a
host-bound render shows as ms per view well above it.
"""

from __future__ import annotations

import argparse
import itertools
import tempfile
import time
from pathlib import Path

import torch

from torch.autograd import DeviceType
from torch.profiler import ProfilerActivity, profile

from ngp_warp.outputs.evaluate import composite_on, depth_to_uint8, evaluate, iter_test_renders, to_uint8
from ngp_warp.outputs.metrics import psnr, ssim
from ngp_warp.training.appearance_fit import fit_appearance_code, nearest_training_code
from ngp_warp.training.checkpoint import load_trainer


def timed_pass(trainer, views: int, work) -> float:
    """ms per view of one pass over ``views`` test views, ``work(out, gt)`` done on each."""
    sync = torch.cuda.synchronize if trainer.device.type == "cuda" else (lambda: None)
    sync()
    start = time.perf_counter()
    for _, out, gt in itertools.islice(iter_test_renders(trainer), views):
        work(out, gt)
    sync()
    return (time.perf_counter() - start) / views * 1e3


def code_parts(trainer, views: int) -> list[tuple[str, float]]:
    """ms per view of each part of the evaluation's code path over ``views`` test views (the
    device synchronised around each part). The code alone is fitted, as for runs without camera
    refinement (a refined run's evaluation fits the pose as well and renders twice)."""
    sync = torch.cuda.synchronize if trainer.device.type == "cuda" else (lambda: None)
    split, background = trainer.scene.test, trainer.view_background
    white = torch.ones(3, device=trainer.device)
    parts = {"code fit": 0.0, "one render, three codes": 0.0, "three renders": 0.0}

    def timed(part: str, work):
        sync()
        start = time.perf_counter()
        result = work()
        sync()
        parts[part] += (time.perf_counter() - start) / views * 1e3
        return result

    for i in range(views):
        camera = split.camera(i)
        gt = composite_on(split.images[i].to(trainer.device), white)
        code = timed("code fit", lambda: fit_appearance_code(trainer, **camera, image=gt, background=background))
        others = (nearest_training_code(trainer, camera["c2w"]), None)
        timed("one render, three codes", lambda: trainer.render_image(**camera, background=background,
                                                                      appearance_code=code, other_codes=others))
        timed("three renders", lambda: [trainer.render_image(**camera, background=background, appearance_code=c)
                                        for c in (code, *others)])
    return list(parts.items())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--views", type=int, default=200)
    args = ap.parse_args()
    trainer, _ = load_trainer(args.run / "checkpoint.pt", device=args.device)
    views = min(args.views, len(trainer.scene.test.names))
    passes = {
        "render": lambda out, gt: None,
        "+ PSNR": lambda out, gt: psnr(out["rgb"], gt),
        "+ SSIM": lambda out, gt: (psnr(out["rgb"], gt), ssim(out["rgb"], gt)),
        "+ images to host": lambda out, gt: (psnr(out["rgb"], gt), ssim(out["rgb"], gt), to_uint8(out["rgb"]).cpu(),
                                             depth_to_uint8(out["depth"], out["opacity"]).cpu()),
    }
    timed_pass(trainer, 2, passes["render"])  # kernels loaded
    rows = [(name, timed_pass(trainer, views, work)) for name, work in passes.items()]
    with tempfile.TemporaryDirectory() as folder:
        start = time.perf_counter()
        evaluate(trainer, Path(folder), show_progress=False)
        whole = (time.perf_counter() - start) / len(trainer.scene.test.names) * 1e3
    rows.append(("evaluate()", whole))
    if trainer.field.appearance is not None:
        rows += code_parts(trainer, views)
    split = trainer.scene.test
    print(f"{views} test views at {split.width}×{split.height}, device {trainer.device}")
    print("| pass | ms per view | s for all test views |\n| --- | ---: | ---: |")
    for name, ms in rows:
        print(f"| {name} | {ms:.1f} | {ms * len(split.names) / 1e3:.1f} |")
    if trainer.device.type == "cuda":
        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
            wall = timed_pass(trainer, 10, passes["render"])
        events = prof.key_averages()
        busy = sum(e.self_device_time_total for e in events if e.device_type == DeviceType.CUDA) / 10 / 1e3
        print(f"render under the profiler: {wall:.1f} ms per view, device busy {busy:.1f} ms per view")
        print(events.table(sort_by="cuda_time_total", row_limit=12, max_name_column_width=60))


if __name__ == "__main__":
    main()
