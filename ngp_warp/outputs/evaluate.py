"""Evaluation (PSNR, SSIM and LPIPS when available, on the test split, white background; with
appearance codes on the right half of each view, its code fitted on the left), renders and depth maps."""

from __future__ import annotations

import dataclasses
import json
from collections import deque
from collections.abc import Iterable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from ngp_warp._wp import cpu_threads
from ngp_warp.progress import progress

from ngp_warp.training.appearance_fit import (FIT_ITERATIONS, FIT_PULL, fit_appearance_and_pose, fit_appearance_code,
                                     nearest_training_code, right_half)
from ngp_warp.atomic import atomic_dir, atomic_write_text
from ngp_warp.outputs.lpips import lpips_scorer, lpips_summary
from ngp_warp.data.loading import Split
from ngp_warp.outputs.metrics import SSIM_WINDOW, psnr_tensor, ssim_tensor
from ngp_warp.training.run_folder import TRAINING_CURVE
from ngp_warp.training.trainer import Trainer


def composite_on(rgba: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """Images as the renders are scored against them: [..., 3|4] uint8 pixels → [..., 3]
    float32 in [0, 1], alpha blended over ``background`` ([3] or broadcastable float)."""
    px = rgba.float() / 255.0
    if px.shape[-1] == 3:
        return px
    a = px[..., 3:]
    return px[..., :3] * a + background * (1.0 - a)


def to_uint8(img: torch.Tensor) -> torch.Tensor:
    """An image in [0, 1] (clamped) as uint8, rounded, on its device."""
    return (img.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8)


def depth_to_uint8(depth: torch.Tensor, opacity: torch.Tensor) -> torch.Tensor:
    """Expected depth normalised by opacity, near = bright, empty = black; [H, W] uint8 on the
    depth's device."""
    d = depth / opacity.clamp_min(1e-6)
    mask = opacity > 0.5
    # the range of the opaque pixels without reading it on the host (no pixel opaque: all black)
    lo = torch.where(mask, d, torch.inf).amin()
    hi = torch.where(mask, d, -torch.inf).amax()
    d = 1.0 - (d - lo) / (hi - lo).clamp_min(1e-6)
    return to_uint8(torch.where(mask, d, torch.zeros_like(d)))


def _cameras_on(split: Split, device: torch.device) -> Split:
    """``split`` with its cameras on ``device``, where every view's rays read them, and its
    images where they are (a test split's go to the device one at a time)."""
    return dataclasses.replace(split, c2w=split.c2w.to(device), intrinsics=split.intrinsics.to(device),
                               distortion=split.distortion.to(device))


def write_workers() -> int:
    """Threads that encode and write an evaluation's images: half the usable cores, 2 to 6.
    Pillow encodes a 400 × 400 render as PNG in about 12 ms on one core (the GIL released), and
    a view writes two images, so two threads take as long as an H200 renders the view."""
    return max(2, min(6, cpu_threads() // 2))


class BackgroundWrites:
    """Image files encoded and written on ``workers`` threads (default :func:`write_workers`)
    while the GPU renders the next view: a context manager whose exit waits for every write and
    raises the first failure; at most four writes a thread queue (each holds its pixels)."""

    def __init__(self, workers: int | None = None):
        workers = workers or write_workers()
        self._pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="image write")
        self._pending: deque[Future] = deque()
        self._max_pending = 4 * workers

    def submit(self, write, *args) -> None:
        while len(self._pending) >= self._max_pending:
            self._pending.popleft().result()
        self._pending.append(self._pool.submit(write, *args))

    def __enter__(self) -> BackgroundWrites:
        return self

    def __exit__(self, exc_type, *exc) -> None:
        try:
            while self._pending and exc_type is None:
                self._pending.popleft().result()
        finally:
            self._pool.shutdown(wait=True, cancel_futures=True)


def iter_test_renders(trainer: Trainer, every: int = 1, split=None, spp: int = 1, fit_appearance: bool = False,
                      nearest_code: bool = False, whole_codes: bool = False):
    """Yield ``(name, render dict, ground truth [H, W, 3])`` for every ``every``-th view of
    ``split`` (default: the test split), rendered (``spp`` as in ``Trainer.render_image``) and
    composited on white; where the field learns the background (``Trainer.black_background``:
    contracted scenes, opaque images) over its learned environment (black for a field without
    one: ``Trainer.view_background``). With appearance codes
    every view is rendered with the mean code of the training images, with ``nearest_code`` the
    code of the training camera nearest to it (:func:`~ngp_warp.training.appearance_fit.nearest_training_code`),
    or, with ``fit_appearance``, with the code fitted on the left half of its ground truth from
    the nearest camera's and pulled toward it
    (:func:`~ngp_warp.training.appearance_fit.fit_appearance_code`, in the render dict as
    ``appearance_code`` [A]): score such a view on the right half only
    (:func:`~ngp_warp.training.appearance_fit.right_half`). When the run refined its training cameras
    (``camera_refinement``), whose corrections move the scene's frame a little, the fit takes the
    view's pose as well (:func:`~ngp_warp.training.appearance_fit.fit_appearance_and_pose`).
    With ``fit_appearance`` and ``whole_codes``, the render dict also holds ``other_rgb`` [2, H,
    W, 3]: the view (at its recorded pose) with the nearest training camera's code and with the
    mean code, coloured from the same samples as the fitted code's where the pose is the same."""
    device = torch.device(trainer.device)
    split = _cameras_on(trainer.scene.test if split is None else split, device)
    white = torch.ones(3, device=device)
    background = trainer.view_background
    codes = trainer.field.appearance is not None
    fit = fit_appearance and codes
    for i in range(0, len(split.names), every):
        camera = split.camera(i)
        # without waiting for the device: CUDA stages a pageable host copy before the call returns
        gt = composite_on(split.images[i].to(device, non_blocking=True), white)
        nearest = nearest_training_code(trainer, camera["c2w"]) if fit or nearest_code and codes else None
        code = None if fit else nearest
        posed, moved = camera, fit and trainer.cameras is not None  # the fit moves the pose too
        if moved:  # the fit starts from the nearest camera's code and is pulled toward it
            code, c2w = fit_appearance_and_pose(trainer, **camera, image=gt, background=background, start=nearest)
            posed = {**camera, "c2w": c2w}
        elif fit:
            code = fit_appearance_code(trainer, **camera, image=gt, background=background, start=nearest)
        others = (nearest, None) if fit and whole_codes else ()
        out = trainer.render_image(**posed, background=background, spp=spp, appearance_code=code,
                                   other_codes=() if moved else others)  # one set of samples at one pose
        if others and moved:  # the other codes' view is at the recorded pose: a render of its own
            whole = trainer.render_image(**camera, background=background, spp=spp, appearance_code=others[0],
                                         other_codes=others[1:])
            out["other_rgb"] = torch.cat([whole["rgb"][None], whole["other_rgb"]])
        if fit:
            out["appearance_code"] = code
        yield split.names[i], out, gt


def _scores(rgb: torch.Tensor, gt: torch.Tensor, lpips_score) -> tuple[dict, str]:
    """PSNR and SSIM (None below an 11-pixel window) as 0-d tensors on the images' device, and
    LPIPS as a float (None and the reason when it cannot be computed: ``lpips_score``, an
    :func:`~ngp_warp.outputs.lpips.lpips_scorer`), of rgb against gt ([H, W, 3] float32 in [0, 1])."""
    s = ssim_tensor(rgb, gt) if min(gt.shape[:2]) >= SSIM_WINDOW else None
    lpips, lpips_note = lpips_score(rgb, gt)
    return {"psnr": psnr_tensor(rgb, gt), "ssim": s, "lpips": lpips}, lpips_note


NEAREST_CODE_KEYS = ("psnr_nearest_code", "psnr_nearest_code_left", "psnr_nearest_code_right")


def psnr_whole_and_halves(rgb: torch.Tensor, gt: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """PSNR of ``rgb`` against ``gt`` ([H, W, 3] float32 each) as three 0-d float64 tensors on
    their device: the whole image, its left half (columns < W // 2) and its right half
    (:func:`right_half`)."""
    half = gt.shape[1] // 2
    return (psnr_tensor(rgb, gt), psnr_tensor(rgb[:, :half], gt[:, :half]),
            psnr_tensor(right_half(rgb), right_half(gt)))


def _nearest_code_scores(rgb: torch.Tensor, gt: torch.Tensor) -> dict:
    """:func:`psnr_whole_and_halves` of a view rendered with the nearest training camera's code."""
    return dict(zip(NEAREST_CODE_KEYS, psnr_whole_and_halves(rgb, gt)))


class _ViewReadout:
    """One scored view, kept on the device until :meth:`read` brings its scores (0-d device
    tensors, None or host floats) and its uint8 render and depth map to the host. Read one view
    later (:func:`_one_behind`), once the next view's render is queued, the host's reads wait
    for the device once a view, not at each score and image, and its file and bookkeeping work
    runs while the device renders."""

    def __init__(self, name: str, out: dict, gt: torch.Tensor, fitted: bool, lpips_score):
        self.name = name
        if fitted:
            scores, self.lpips_note = _scores(right_half(out["rgb"]), right_half(gt), lpips_score)
            nearest, mean = out["other_rgb"]
            scores["psnr_mean_code"] = psnr_tensor(mean, gt)
            scores.update(_nearest_code_scores(nearest, gt))
        else:
            scores, self.lpips_note = _scores(out["rgb"], gt, lpips_score)
        self._scores = scores
        self._images = (to_uint8(out["rgb"]), depth_to_uint8(out["depth"], out["opacity"]))

    def read(self) -> tuple[dict, np.ndarray, np.ndarray]:
        """The scores as host floats (in their order; None where not computed), the render [H, W,
        3] and the depth map [H, W] uint8."""
        on_device = [k for k, v in self._scores.items() if isinstance(v, torch.Tensor)]
        values = dict(zip(on_device, torch.stack([self._scores[k] for k in on_device]).tolist()))
        scores = {k: values.get(k, v) for k, v in self._scores.items()}
        return scores, *(t.cpu().numpy() for t in self._images)


def _one_behind(items: Iterable) -> Iterator:
    """``items`` in order, each yielded once the next one has been made (the last at the end)."""
    previous = marker = object()
    for item in items:
        if previous is not marker:
            yield previous
        previous = item
    if previous is not marker:
        yield previous


def evaluate(trainer: Trainer, out_dir: Path, show_progress: bool = True) -> dict:
    """Render every test view, score it, write renders/ depth/ and metrics.json.

    With per-image appearance codes a test view has no code of its own: it is rendered with the
    code fitted on the left half of its image and scored (psnr, ssim, lpips) on the right half,
    which the fit did not see, as nerfstudio does. Its whole image is scored twice: with the
    code of the nearest training camera (``psnr_nearest_code``; its left and right halves too,
    ``psnr_nearest_code_left`` and ``_right``, so that the right half shows what the fitted code
    gains over the nearest one) and with the mean training code (``psnr_mean_code``);
    metrics.json's ``appearance`` says so. renders/ holds the fitted code's whole images."""
    out_dir = Path(out_dir)
    fitted = trainer.field.appearance is not None
    views = iter_test_renders(trainer, fit_appearance=fitted, whole_codes=True)
    per_image = []
    bar = progress(desc="eval", total=len(trainer.scene.test.names), unit="view", disable=not show_progress)
    with trainer.weights.averaged_in_field(), atomic_dir(out_dir / "renders") as renders, \
            atomic_dir(out_dir / "depth") as depths, BackgroundWrites() as writes:  # the average swapped in once
        lpips_score = lpips_scorer()
        for view in _one_behind(_ViewReadout(name, out, gt, fitted, lpips_score) for name, out, gt in views):
            stem, lpips_note = Path(view.name).stem, view.lpips_note
            scores, rgb, depth = view.read()
            per_image.append({"image": view.name, **scores})
            writes.submit(iio.imwrite, renders / f"{stem}.png", rgb)
            writes.submit(iio.imwrite, depths / f"{stem}.png", depth)
            bar.set_postfix(psnr=f"{scores['psnr']:.2f}", refresh=False)
            bar.update()
        bar.close()
    posed = " and pose" if trainer.cameras is not None else ""
    appearance = {"appearance": f"code{posed} fitted on the left half ({FIT_ITERATIONS} iterations from the nearest "
                                f"training camera's code, pulled toward it with weight {FIT_PULL:g}), scored on "
                                f"the right half; whole images with the nearest training camera's code "
                                f"(psnr_nearest_code, its halves psnr_nearest_code_left and _right) and the mean "
                                f"code (psnr_mean_code)",
                  **{key: float(np.mean([m[key] for m in per_image])) for key in NEAREST_CODE_KEYS + ("psnr_mean_code",)}
                  } if fitted else {}
    metrics = {
        "psnr": float(np.mean([m["psnr"] for m in per_image])),
        "ssim": None if per_image[0]["ssim"] is None else float(np.mean([m["ssim"] for m in per_image])),
        **lpips_summary([m["lpips"] for m in per_image], lpips_note),
        "train_seconds": trainer.train_seconds,
        "steps": trainer.step_count,
        "train_samples_per_ray": trainer.target_samples / trainer.rays.n_rays,
        "device": str(trainer.device),
        "test_split": "held-out training frames" if trainer.scene.test_is_heldout else "test",
        "n_test_images": len(per_image),
        **appearance,
        "per_image": per_image,
    }
    return write_metrics(out_dir, metrics)


def write_metrics(out_dir: Path, metrics: dict) -> dict:
    """Write ``metrics`` (non-finite numbers as null) to ``out_dir/metrics.json``; return what was written."""
    metrics = finite_or_null(metrics)
    atomic_write_text(Path(out_dir) / "metrics.json", json.dumps(metrics, indent=2, allow_nan=False))
    return metrics


CURVE_COLUMNS = ("step", "seconds", "loss", "psnr", "rays", "samples")


def write_training_curve(out_dir: Path, rows: Sequence[tuple]) -> Path:
    """Write the trainer's readouts (:attr:`~ngp_warp.training.trainer.Trainer.curve`: step,
    training seconds, loss, training-batch PSNR, rays and samples of that step) to
    ``out_dir/training_curve.csv``, one row each; return its path."""
    lines = [",".join(CURVE_COLUMNS)]
    lines += [f"{step},{seconds:.3f},{loss:.6g},{psnr:.4f},{rays},{samples}"
              for step, seconds, loss, psnr, rays, samples in rows]
    path = Path(out_dir) / TRAINING_CURVE
    atomic_write_text(path, "\n".join(lines) + "\n")
    return path


def finite_or_null(metrics: dict) -> dict:
    """``metrics`` with every NaN or infinite number (nested ones too) replaced by None, and a
    ``notes`` entry naming them, so that the JSON is strict (no bare NaN)."""
    replaced = []

    def clean(value, where: str):
        if isinstance(value, float) and not np.isfinite(value):
            replaced.append(f"{where} ({value})")
            return None
        if isinstance(value, dict):
            return {k: clean(v, f"{where}.{k}" if where else k) for k, v in value.items()}
        if isinstance(value, list):
            return [clean(v, f"{where}[{i}]") for i, v in enumerate(value)]
        return value

    cleaned = clean(metrics, "")
    if replaced:
        note = f"not finite, written as null: {', '.join(replaced[:5])}{' ...' if len(replaced) > 5 else ''}"
        cleaned["notes"] = [*cleaned.get("notes", []), note]
    return cleaned

