"""Evaluation (PSNR, SSIM and LPIPS when available, on the test split, white background; with
appearance codes on the right half of each view, its code fitted on the left), renders and depth maps."""

from __future__ import annotations

import json
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from ngp_warp.progress import progress

from ngp_warp.training.appearance_fit import (FIT_ITERATIONS, fit_appearance_and_pose, fit_appearance_code,
                                     nearest_training_code, right_half)
from ngp_warp.atomic import atomic_dir, atomic_write_text
from ngp_warp.outputs.lpips import lpips_or_reason, lpips_summary
from ngp_warp.outputs.metrics import SSIM_WINDOW, psnr_images, ssim_images
from ngp_warp.training.trainer import Trainer


def composite_on(rgba: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """Images as the renders are scored against them: [..., 3|4] uint8 pixels → [..., 3]
    float32 in [0, 1], alpha blended over ``background`` ([3] or broadcastable float)."""
    px = rgba.float() / 255.0
    if px.shape[-1] == 3:
        return px
    a = px[..., 3:]
    return px[..., :3] * a + background * (1.0 - a)


def to_uint8(img: torch.Tensor) -> np.ndarray:
    return (img.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()


def depth_to_uint8(depth: torch.Tensor, opacity: torch.Tensor) -> np.ndarray:
    """Expected depth normalised by opacity, near = bright, empty = black: [..., H, W] float32
    each → [..., H, W] uint8, each image scaled to its own range."""
    d = depth / opacity.clamp_min(1e-6)
    mask = opacity > 0.5
    # the range of the opaque pixels without reading it on the host (no pixel opaque: all black)
    lo = torch.where(mask, d, torch.inf).amin(dim=(-2, -1), keepdim=True)
    hi = torch.where(mask, d, -torch.inf).amax(dim=(-2, -1), keepdim=True)
    d = 1.0 - (d - lo) / (hi - lo).clamp_min(1e-6)
    return to_uint8(torch.where(mask, d, torch.zeros_like(d)))


class BackgroundWrites:
    """Image files encoded and written on two threads while the GPU renders the next view: a
    context manager whose exit waits for every write and raises the first failure; at most
    ``max_pending`` writes queue (each holds its pixels)."""

    def __init__(self, max_pending: int = 8):
        self._pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="image write")
        self._pending: deque[Future] = deque()
        self._max_pending = max_pending

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
                      nearest_code: bool = False, whole_codes: bool = False, views_per_render: int = 1):
    """Yield ``(name, render dict, ground truth [H, W, 3])`` for every ``every``-th view of
    ``split`` (default: the test split), rendered (``spp`` as in ``Trainer.render_image``) and
    composited on white; where the field learns the background (``Trainer.black_background``:
    contracted scenes, opaque images) over its learned environment (black for a field without
    one: ``Trainer.view_background``). With appearance codes
    every view is rendered with the mean code of the training images, with ``nearest_code`` the
    code of the training camera nearest to it (:func:`~ngp_warp.training.appearance_fit.nearest_training_code`),
    or, with ``fit_appearance``, with the code fitted on the left half of its ground truth
    (:func:`~ngp_warp.training.appearance_fit.fit_appearance_code`, in the render dict as
    ``appearance_code`` [A]): score such a view on the right half only
    (:func:`~ngp_warp.training.appearance_fit.right_half`). When the run refined its training cameras
    (``camera_refinement``), whose corrections move the scene's frame a little, the fit takes the
    view's pose as well (:func:`~ngp_warp.training.appearance_fit.fit_appearance_and_pose`).
    With ``fit_appearance`` and ``whole_codes``, the render dict also holds ``other_rgb`` [2, H,
    W, 3]: the view (at its recorded pose) with the nearest training camera's code and with the
    mean code, coloured from the same samples as the fitted code's where the pose is the same.
    Where no view has a code of its own (no fit, no nearest code), ``views_per_render`` views are
    rendered in one call (:func:`~ngp_warp.outputs.renderer.render_view` with a batch of cameras),
    each view's dict then holding its ``rgb``, ``depth`` and ``opacity`` alone."""
    split = trainer.scene.test if split is None else split
    white = torch.ones(3, device=trainer.device)
    background = trainer.view_background
    fit = fit_appearance and trainer.field.appearance is not None
    if views_per_render > 1 and not fit and not (nearest_code and trainer.field.appearance is not None):
        yield from _views_together(trainer, split, range(0, len(split.names), every), views_per_render, spp)
        return
    for i in range(0, len(split.names), every):
        camera = split.camera(i)
        gt = composite_on(split.images[i].to(trainer.device), white)
        code = None
        if nearest_code and trainer.field.appearance is not None and not fit:
            code = nearest_training_code(trainer, camera["c2w"])
        posed, moved = camera, fit and trainer.cameras is not None  # the fit moves the pose too
        if moved:
            code, c2w = fit_appearance_and_pose(trainer, **camera, image=gt, background=background)
            posed = {**camera, "c2w": c2w}
        elif fit:
            code = fit_appearance_code(trainer, **camera, image=gt, background=background)
        others = (nearest_training_code(trainer, camera["c2w"]), None) if fit and whole_codes else ()
        out = trainer.render_image(**posed, background=background, spp=spp, appearance_code=code,
                                   other_codes=() if moved else others)  # one set of samples at one pose
        if others and moved:  # the other codes' view is at the recorded pose: a render of its own
            whole = trainer.render_image(**camera, background=background, spp=spp, appearance_code=others[0],
                                         other_codes=others[1:])
            out["other_rgb"] = torch.cat([whole["rgb"][None], whole["other_rgb"]])
        if fit:
            out["appearance_code"] = code
        yield split.names[i], out, gt


def _views_together(trainer: Trainer, split, indices: range, views_per_render: int, spp: int):
    """:func:`iter_test_renders` of views without codes of their own, ``views_per_render`` to a render."""
    white = torch.ones(3, device=trainer.device)
    for lo in range(0, len(indices), views_per_render):
        group = list(indices[lo:lo + views_per_render])
        out = trainer.render_image(split.c2w[group], split.intrinsics[group], split.width, split.height,
                                   distortion=split.distortion[group] if split.has_distortion else None,
                                   fisheye=split.fisheye, background=trainer.view_background, spp=spp)
        for k, i in enumerate(group):
            view = {key: out[key][k] for key in ("rgb", "depth", "opacity")}
            yield split.names[i], view, composite_on(split.images[i].to(trainer.device), white)


NEAREST_CODE_KEYS = ("psnr_nearest_code", "psnr_nearest_code_left", "psnr_nearest_code_right")


def _whole_and_halves(rgb: torch.Tensor, gt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """PSNR [B] float64 of B renders against their truths ([B, H, W, 3] float32 each), on the
    device: whole images, left halves (columns < W // 2), right halves (:func:`right_half`)."""
    half = gt.shape[2] // 2
    return (psnr_images(rgb, gt), psnr_images(rgb[:, :, :half], gt[:, :, :half]),
            psnr_images(right_half(rgb), right_half(gt)))


def psnr_whole_and_halves(rgb: torch.Tensor, gt: torch.Tensor) -> tuple[float, float, float]:
    """PSNR of ``rgb`` against ``gt`` ([H, W, 3] float32 each): the whole image, its left half
    (columns < W // 2) and its right half (:func:`right_half`)."""
    return tuple(torch.cat(_whole_and_halves(rgb[None], gt[None])).tolist())


def _score_views(outs: list[dict], gts: list[torch.Tensor], fitted: bool) -> tuple[list[dict], str]:
    """Each view's scores, read from the device together: ``psnr``, ``ssim`` (None below an
    11-pixel window) and ``lpips`` (None when it cannot be computed; the returned note says why)
    of its render (``rgb`` [H, W, 3] of each render dict in ``outs``) against its truth ([H, W, 3]
    float32 in [0, 1], one size for all); with codes fitted on the left halves (``fitted``) on
    the right halves, and with the whole images' ``psnr_mean_code`` and the nearest code's
    scores (:data:`NEAREST_CODE_KEYS`) of each render's ``other_rgb``."""
    truth, rgb = torch.stack(gts), torch.stack([out["rgb"] for out in outs])
    scored, scored_truth = (right_half(rgb), right_half(truth)) if fitted else (rgb, truth)
    columns = {"psnr": psnr_images(scored, scored_truth)}
    if min(truth.shape[1:3]) >= SSIM_WINDOW:
        columns["ssim"] = ssim_images(scored, scored_truth)
    if fitted:
        nearest, mean = torch.stack([out["other_rgb"] for out in outs]).unbind(1)
        columns["psnr_mean_code"] = psnr_images(mean, truth)
        columns.update(zip(NEAREST_CODE_KEYS, _whole_and_halves(nearest, truth)))
    read = dict(zip(columns, torch.stack(list(columns.values())).tolist()))  # one wait for the device
    views, note = [], ""
    for k in range(len(outs)):
        lpips, note = lpips_or_reason(scored[k], scored_truth[k])
        views.append({"psnr": read["psnr"][k], "ssim": read["ssim"][k] if "ssim" in read else None, "lpips": lpips,
                      **{key: values[k] for key, values in read.items() if key not in ("psnr", "ssim")}})
    return views, note


def _groups(items, size: int):
    """Lists of ``size`` consecutive items (the last may be shorter)."""
    group = []
    for item in items:
        group.append(item)
        if len(group) == size:
            yield group
            group = []
    if group:
        yield group


EVAL_VIEWS_TOGETHER = 4  # test views rendered and scored at a time: fewer launches and host waits a view


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
    views = iter_test_renders(trainer, fit_appearance=fitted, whole_codes=True, views_per_render=EVAL_VIEWS_TOGETHER)
    per_image = []
    bar = progress(desc="eval", total=len(trainer.scene.test.names), unit="view", disable=not show_progress)
    with atomic_dir(out_dir / "renders") as renders, atomic_dir(out_dir / "depth") as depths, \
            BackgroundWrites() as writes:
        for group in _groups(views, EVAL_VIEWS_TOGETHER):
            names, outs, gts = zip(*group)
            scores, lpips_note = _score_views(outs, gts, fitted)
            images = to_uint8(torch.stack([out["rgb"] for out in outs]))
            depth = depth_to_uint8(torch.stack([out["depth"] for out in outs]),
                                   torch.stack([out["opacity"] for out in outs]))
            for name, view_scores, image, view_depth in zip(names, scores, images, depth):
                per_image.append({"image": name, **view_scores})
                writes.submit(iio.imwrite, renders / f"{Path(name).stem}.png", image)
                writes.submit(iio.imwrite, depths / f"{Path(name).stem}.png", view_depth)
            bar.set_postfix(psnr=f"{scores[-1]['psnr']:.2f}", refresh=False)
            bar.update(len(group))
        bar.close()
    posed = " and pose" if trainer.cameras is not None else ""
    appearance = {"appearance": f"code{posed} fitted on the left half ({FIT_ITERATIONS} iterations), scored on "
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

