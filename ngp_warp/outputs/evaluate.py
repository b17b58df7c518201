"""Evaluation (PSNR, SSIM and LPIPS when available, on the test split, white background; with
appearance codes on the right half of each view, its code fitted on the left), renders and depth maps."""

from __future__ import annotations

import dataclasses
import itertools
import json
from collections import deque
from collections.abc import Iterable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from ngp_warp._wp import cpu_threads
from ngp_warp.progress import progress

from ngp_warp.training.appearance_fit import (FIT_ITERATIONS, FIT_PULL, fit_appearance_and_pose, fit_appearance_code,
                                     nearest_training_code, right_half)
from ngp_warp.atomic import atomic_dir, atomic_write_text
from ngp_warp.outputs.lpips import lpips_scorer, lpips_summary
from ngp_warp.data.loading import Split
from ngp_warp.outputs.metrics import SSIM_WINDOW, psnr_batch, psnr_tensor, ssim_batch
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
    """Expected depth normalised by opacity, near = bright, empty = black: [..., H, W] uint8 on
    the depth's device, each image ([H, W]) over the range of its own opaque pixels."""
    d = depth / opacity.clamp_min(1e-6)
    mask = opacity > 0.5
    # the range of the opaque pixels without reading it on the host (no pixel opaque: all black)
    lo = torch.where(mask, d, torch.inf).amin(dim=(-2, -1), keepdim=True)
    hi = torch.where(mask, d, -torch.inf).amax(dim=(-2, -1), keepdim=True)
    d = 1.0 - (d - lo) / (hi - lo).clamp_min(1e-6)
    return to_uint8(torch.where(mask, d, torch.zeros_like(d)))


def _cameras_on(split: Split, device: torch.device) -> Split:
    """``split`` with its cameras on ``device``, where every view's rays read them, and its
    images where they are (a test split's go to the device one at a time)."""
    return dataclasses.replace(split, c2w=split.c2w.to(device), intrinsics=split.intrinsics.to(device),
                               distortion=split.distortion.to(device))


def write_png(path: Path, pixels: np.ndarray) -> None:
    """``pixels`` ([H, W, 3] or [H, W] uint8) as a PNG file, by Pillow directly: the file imageio
    writes, without its per-call plugin lookup, which holds the GIL that the renders' launches need."""
    Image.fromarray(pixels).save(path, format="PNG")


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


NEAREST_CODE_KEYS = ("psnr_nearest_code", "psnr_nearest_code_left", "psnr_nearest_code_right")
SCORE_GROUP_PIXELS = 1 << 21  # pixels of the test views scored together: 8 lego views (400 × 400)
MAX_SCORE_GROUP = 8


def psnr_whole_and_halves(rgb: torch.Tensor, gt: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """PSNR of ``rgb`` against ``gt`` ([H, W, 3] float32 each) as three 0-d float64 tensors on
    their device: the whole image, its left half (columns < W // 2) and its right half
    (:func:`right_half`)."""
    half = gt.shape[1] // 2
    return (psnr_tensor(rgb, gt), psnr_tensor(rgb[:, :half], gt[:, :half]),
            psnr_tensor(right_half(rgb), right_half(gt)))


def _score_pairs(out: dict, gt: torch.Tensor, fitted: bool) -> dict:
    """What a view is scored on, in metrics.json's order: {key: (metric, render, ground truth)}
    with metric "psnr" or "ssim" (and "lpips" for LPIPS), images [H', W', 3] float32. A fitted
    view (appearance codes) scores its fitted code's right half, its mean code's whole image and
    its nearest code's whole image and halves (:func:`psnr_whole_and_halves`)."""
    rgb, ref = (right_half(out["rgb"]), right_half(gt)) if fitted else (out["rgb"], gt)
    pairs = {"psnr": ("psnr", rgb, ref), "ssim": ("ssim", rgb, ref), "lpips": ("lpips", rgb, ref)}
    if fitted:
        nearest, mean = out["other_rgb"]
        half = gt.shape[1] // 2
        pairs["psnr_mean_code"] = ("psnr", mean, gt)
        pairs.update(zip(NEAREST_CODE_KEYS, (("psnr", nearest, gt), ("psnr", nearest[:, :half], gt[:, :half]),
                                             ("psnr", right_half(nearest), right_half(gt)))))
    return pairs


def score_group_size(width: int, height: int) -> int:
    """Test views of ``width`` × ``height`` scored together: :data:`SCORE_GROUP_PIXELS` of them,
    1 to :data:`MAX_SCORE_GROUP` views."""
    return max(1, min(MAX_SCORE_GROUP, SCORE_GROUP_PIXELS // max(1, width * height)))


class _GroupReadout:
    """A group of rendered views ``(name, render dict, ground truth)``, scored together on the
    device (:func:`~ngp_warp.outputs.metrics.psnr_batch`, :func:`~ngp_warp.outputs.metrics.ssim_batch`:
    a set of score launches a group instead of a view) and kept there until :meth:`read` brings
    every score and the uint8 renders and depth maps to the host in one wait. Read one group
    later (:func:`_one_behind`), once the next group's renders are queued, the host's file and
    bookkeeping work runs while the device renders. LPIPS, where available, is scored a view at
    a time (``lpips_score``, :func:`~ngp_warp.outputs.lpips.lpips_scorer`)."""

    def __init__(self, views: list, fitted: bool, lpips_score):
        self.names = [name for name, _, _ in views]
        pairs = [_score_pairs(out, gt, fitted) for _, out, gt in views]
        lpips = [lpips_score(*view["lpips"][1:]) for view in pairs]
        self.lpips_note = lpips[-1][1]
        self._lpips = [value for value, _ in lpips]
        self._keys = list(pairs[0])
        small = min(pairs[0]["ssim"][2].shape[:2]) < SSIM_WINDOW  # SSIM needs its whole window
        self._on_device = [key for key in self._keys if key != "lpips" and not (key == "ssim" and small)]
        batched = {"psnr": psnr_batch, "ssim": ssim_batch}
        scores = []
        for key in self._on_device:
            renders, truths = (torch.stack([view[key][i] for view in pairs]) for i in (1, 2))
            scores.append(batched[pairs[0][key][0]](renders, truths))
        self._scores = torch.stack(scores)  # [K, G] float64
        self._images = (to_uint8(torch.stack([out["rgb"] for _, out, _ in views])),
                        depth_to_uint8(torch.stack([out["depth"] for _, out, _ in views]),
                                       torch.stack([out["opacity"] for _, out, _ in views])))

    def read(self) -> list[tuple[str, dict, np.ndarray, np.ndarray]]:
        """Each view's name, scores as host floats (in metrics.json's order; None where not
        computed), render [H, W, 3] and depth map [H, W] uint8."""
        values = self._scores.T.tolist()  # [G][K]
        rgbs, depths = (images.cpu().numpy() for images in self._images)
        read = []
        for k, name in enumerate(self.names):
            known = dict(zip(self._on_device, values[k]), lpips=self._lpips[k])
            read.append((name, {key: known.get(key) for key in self._keys}, rgbs[k], depths[k]))
        return read


def _groups(items: Iterable, size: int) -> Iterator[list]:
    """``items`` in lists of ``size`` (the last may be shorter)."""
    items = iter(items)
    while group := list(itertools.islice(items, size)):
        yield group


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
        size = score_group_size(trainer.scene.test.width, trainer.scene.test.height)
        groups = (_GroupReadout(group_views, fitted, lpips_score) for group_views in _groups(views, size))
        for group in _one_behind(groups):
            lpips_note = group.lpips_note
            for name, scores, rgb, depth in group.read():
                per_image.append({"image": name, **scores})
                writes.submit(write_png, renders / f"{Path(name).stem}.png", rgb)
                writes.submit(write_png, depths / f"{Path(name).stem}.png", depth)
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

