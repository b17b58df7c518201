"""``ngp-warp process INPUT --out SCENE``: photos or a video -> a posed scene, by structure from
motion with pycolmap (the ``[process]`` extra).

Stages, each with a progress bar: frames (a video only: the sharpest of each stretch, see
:mod:`ngp_warp.data.video`) -> SIFT features (dense, on the CPU, or COLMAP's standard ones, on the
GPU when pycolmap has CUDA) -> matching (sequential for a video, whose frames overlap their
neighbours; exhaustive for a photo set of up to :data:`EXHAUSTIVE_MAX` images) -> global (or
incremental) mapping, checked against the images' own matches (a model folded by the subject's
symmetry is mapped again by the other mapper, and reported if that does not help:
:mod:`ngp_warp.data.fold_check`). SCENE then holds ``images/``,
``sparse/0`` (the COLMAP model, binary), ``transforms.json`` (instant-ngp format, the scene
normalised by :func:`ngp_warp.data.colmap.colmap_to_transforms`) and, with masks, ``masks/``
(:mod:`ngp_warp.data.process_masks`).

SCENE is built in a temporary sibling folder renamed into place at the end: a failure or Ctrl-C
leaves nothing behind, and an existing SCENE is replaced only when asked (``overwrite``).
"""

from __future__ import annotations

import contextlib
import json
import shutil
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from ngp_warp.data.data_error import DataError
from ngp_warp.data.process_photos import gather_photos
from ngp_warp.data.database_rows import DatabaseRows
from ngp_warp.data.pose_errors import pose_errors  # noqa: F401  (process's callers check poses with it)
from ngp_warp.data.process_masks import check_masks, gather_masks, name_masks

EXTRA = 'pip install "ngp-warp[process]"'
EXHAUSTIVE_MAX = 300  # photo sets up to this size match every pair; larger ones match by name order
SEQUENTIAL_OVERLAP = 10  # sequential matching: each image against its next 10 (and 2^k-th) neighbours
MIN_REGISTERED = 3
MAPPING_SEED = 0  # fixed RANSAC and mapper seed: the same matches give the same poses
CAMERA_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "OPENCV_FISHEYE")
SIFT_KINDS = ("dense", "standard")  # dense: more features, affine shapes, domain-size pooling (CPU SIFT)
MAPPERS = ("global", "incremental")  # COLMAP's global mapper (GLOMAP) or its incremental one
DENSE_SIFT_FEATURES = 16384
# Verified matches a pair needs (COLMAP's default: 15). On 40 of lego's views over white, the
# weak false matches between its front and back folded the global mapper's model in 10 of 14 runs
# at 15, in none of 10 at 30 and of 5 at 40; true neighbours share 100-450.
VERIFY_MIN_INLIERS = 30


@dataclass
class ProcessConfig:
    """How ``process`` runs.

    frames, fps: a video gives this many frames (evenly spread) or this many per second (one of
        the two; ``frames`` defaults to 100); refused for a folder of photos.
    matcher: ``auto`` (sequential for a video or more than EXHAUSTIVE_MAX photos, else exhaustive),
        ``exhaustive`` or ``sequential`` (photos in file-name order).
    camera_model: the COLMAP camera model, one camera shared by every image (all of one size).
        SIMPLE_RADIAL (f, cx, cy, k1) is COLMAP's default; OPENCV's extra freedom settled
        on a wrong focal length (and mirrored poses) for the 256-px views of the test scene.
    device: SIFT on ``auto`` (the GPU when pycolmap has CUDA), ``cpu`` or ``cuda`` (``dense``
        SIFT runs on the CPU: COLMAP's GPU SIFT has no affine shapes).
    sift: ``dense`` (up to 16384 features an image, affine shapes, domain-size pooling) or
        ``standard`` (COLMAP's defaults). mapper: ``global`` or ``incremental``. On 40 of
        lego's views over white (2 CPU cores, benchmarks/RESULTS.md) standard + incremental
        registered 26 at 0.21° median error, dense + incremental 39 but folded by the model's
        symmetry (13.7°), standard + global 40 folded (5.9°), dense + global 40 at 0.26°
        (in 4 of 14 runs with COLMAP's 15 verified matches a pair, in 5 of 5 with 30); on
        fox's 50 photos dense + global 50 at 0.60° (0.7° at most), as the standard incremental
        run's 0.71°; on the demo room both 40 of 40 at 0.03°.
    masks: a folder with a mask per photo (``NAME.png`` or ``STEM.png``; a pixel is kept where
        its first channel is nonzero): no features where a mask leaves pixels out, and the
        scene's frames name the masks for training (:mod:`ngp_warp.data.process_masks`).
        Photos only.
    overwrite: replace an existing SCENE.
    show_progress: progress bars on stderr.
    """

    frames: int | None = None
    fps: float | None = None
    matcher: str = "auto"
    camera_model: str = "SIMPLE_RADIAL"
    device: str = "auto"
    sift: str = "dense"
    mapper: str = "global"
    masks: str | Path | None = None
    overwrite: bool = False
    show_progress: bool = True

    def check(self) -> None:
        if self.frames is not None and self.fps is not None:
            raise ValueError("give --frames or --fps, not both")
        for name in ("frames", "fps"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise ValueError(f"{name} must be positive, got {value!r}")
        choices = {"matcher": ("auto", "exhaustive", "sequential"), "camera_model": CAMERA_MODELS,
                   "device": ("auto", "cpu", "cuda"), "sift": SIFT_KINDS, "mapper": MAPPERS}
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {', '.join(allowed)}, got {getattr(self, name)!r}")


@dataclass
class ProcessReport:
    """What ``process`` made: ``registered`` of ``total`` images posed, the model's mean
    reprojection error in pixels, the matcher, SIFT device and mapper used, wall-clock seconds
    per stage, and the images whose poses contradict their own matches
    (:func:`ngp_warp.data.fold_check.contradicted_images`; empty for a sound model)."""

    scene: Path
    registered: int
    total: int
    mean_reprojection_error: float
    matcher: str
    sift_device: str
    mapper: str
    contradicted: list
    seconds: dict


def require_pycolmap():
    """The pycolmap module, or a DataError naming the extra to install."""
    try:
        import imageio_ffmpeg  # noqa: F401  (frames from videos)
        import pycolmap
    except ImportError as e:
        raise DataError(f"process needs pycolmap and imageio-ffmpeg ({e.name} is not installed): {EXTRA}") from None
    return pycolmap


def _run_stage(label: str, total: int, work, progress, show: bool):
    """Run ``work(cancel_token)`` (a pycolmap call, which releases the GIL) in a thread while a
    progress bar, when ``show``, moves to ``progress`` of ``total``: a callable giving the count
    done, or (database, table) whose rows count; Ctrl-C cancels the call before it propagates."""
    import pycolmap
    from ngp_warp.progress import progress as progress_bar

    token, outcome = pycolmap.CancellationToken(), {}

    def target():
        try:
            outcome["value"] = work(token)
        except BaseException as e:  # handed to the main thread
            outcome["error"] = e

    thread = threading.Thread(target=target, name=f"pycolmap {label}", daemon=True)
    with progress_bar(total=total, desc=label, unit="", disable=not show) as bar, contextlib.ExitStack() as stack:
        if isinstance(progress, tuple):
            progress = stack.enter_context(DatabaseRows(*progress)).rows if show else (lambda: None)
        thread.start()
        try:
            while thread.is_alive():
                thread.join(0.25)
                done = progress()
                if done is not None:
                    bar.update(min(done, total) - bar.n)
        except KeyboardInterrupt:
            token.cancel()
            thread.join()
            raise
        bar.update(total - bar.n)
    if "error" in outcome:
        raise outcome["error"]
    return outcome.get("value")


def sequential_pairs(n_images: int, overlap: int = SEQUENTIAL_OVERLAP) -> int:
    """How many pairs sequential matching (with quadratic overlap) visits among ``n_images``."""
    steps = set(range(1, overlap + 1)) | {2 ** k for k in range(overlap)}
    return sum(max(n_images - step, 0) for step in steps)


def _sift_device(pycolmap, name: str):
    if name == "cuda" and not pycolmap.has_cuda:
        raise DataError("--device cuda: this pycolmap was built without CUDA (use --device cpu or auto)")
    return pycolmap.Device.cuda if name != "cpu" and pycolmap.has_cuda else pycolmap.Device.cpu


def _features_and_matches(work: Path, images_dir: Path, sizes: dict, matcher: str, config: ProcessConfig,
                          masks: Path | None):
    """SIFT features of every image (none where its mask in ``masks`` is 0), then matched and
    verified pairs, into ``work/database.db``."""
    import pycolmap

    database, device, show = work / "database.db", _sift_device(pycolmap, config.device), config.show_progress
    reader = pycolmap.ImageReaderOptions(camera_model=config.camera_model)
    if masks is not None:
        reader.mask_path = str(masks)
    extraction = pycolmap.FeatureExtractionOptions()
    if config.sift == "dense":
        extraction.sift.max_num_features = DENSE_SIFT_FEATURES
        extraction.sift.estimate_affine_shape = extraction.sift.domain_size_pooling = True
    sift_device = pycolmap.Device.cpu if config.sift == "dense" else device
    _run_stage("features", len(sizes), lambda token: pycolmap.extract_features(
        database, images_dir, image_names=list(sizes), camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
        extraction_options=extraction, device=sift_device, cancellation_token=token),
        (database, "keypoints"), show)
    n = len(sizes)
    if matcher == "exhaustive":
        pairs, run = n * (n - 1) // 2, pycolmap.match_exhaustive
        options = pycolmap.ExhaustivePairingOptions()
    else:
        pairs, run = sequential_pairs(n), pycolmap.match_sequential
        options = pycolmap.SequentialPairingOptions(overlap=SEQUENTIAL_OVERLAP, quadratic_overlap=True)
    verification = pycolmap.TwoViewGeometryOptions()
    verification.min_num_inliers = VERIFY_MIN_INLIERS
    _run_stage(f"matching ({matcher})", pairs, lambda token: run(
        database, pairing_options=options, verification_options=verification, device=device, cancellation_token=token),
        (database, "two_view_geometries"), show)
    return database, "cuda" if sift_device == pycolmap.Device.cuda else "cpu"


def _mapping(work: Path, database: Path, images_dir: Path, n_images: int, show: bool, mapper: str):
    """Global or incremental mapping: the one model of the registered images, or a DataError."""
    import pycolmap

    registered = [0]

    def on_pair():
        registered[0] += 2

    def on_image():
        registered[0] += 1

    def run(token):
        if mapper == "global":  # one solve: its bar moves once, at the end
            options = pycolmap.GlobalPipelineOptions(random_seed=MAPPING_SEED)
            return pycolmap.global_mapping(database, images_dir, models_dir, options=options)
        options = pycolmap.IncrementalPipelineOptions(random_seed=MAPPING_SEED)
        return pycolmap.incremental_mapping(database, images_dir, models_dir, options=options,
                                            initial_image_pair_callback=on_pair,
                                            next_image_callback=on_image, cancellation_token=token)

    models_dir = work / f"models-{mapper}"
    models_dir.mkdir()
    models = _run_stage(f"mapping ({mapper})", n_images, run, lambda: registered[0], show)
    if not models:
        raise DataError(f"structure from motion failed: no two of the {n_images} images match well enough "
                        f"to start a model (more overlap between views, more texture, less blur)")
    by_size = sorted(models.values(), key=lambda m: -m.num_reg_images())
    model, posed = by_size[0], {image.name for image in by_size[0].images.values() if image.has_pose}
    for other in by_size[1:]:  # COLMAP's later models may reuse images of the first; only new ones split it
        apart = {image.name for image in other.images.values() if image.has_pose} - posed
        if len(apart) >= MIN_REGISTERED:
            raise DataError(f"structure from motion split the {n_images} images into separate models "
                            f"({model.num_reg_images()} images, and {len(apart)} others on their own): "
                            f"add views that join them")
    if model.num_reg_images() < MIN_REGISTERED:
        raise DataError(f"structure from motion registered only {model.num_reg_images()} of {n_images} images "
                        f"(at least {MIN_REGISTERED} are needed)")
    return model


def _sound_mapping(work: Path, database: Path, images_dir: Path, n_images: int, config: ProcessConfig):
    """(model, mapper, contradicted images): the model of ``config.mapper``; when some of its
    images contradict their own matches (a model folded by the subject's symmetry), the other
    mapper's too, keeping the one with fewer contradicted images (the first on a tie). On lego's
    views a fold of one mapper was once undone by the other and once shared by it; another seed
    of the same mapper gave the same fold."""
    from ngp_warp.data.fold_check import contradicted_images, database_inliers, model_axes

    def mapped(mapper):
        model = _mapping(work, database, images_dir, n_images, config.show_progress, mapper)
        return model, mapper, contradicted_images(model_axes(model), database_inliers(database, model))

    first = mapped(config.mapper)
    if not first[2]:
        return first
    try:
        second = mapped(next(m for m in MAPPERS if m != config.mapper))
    except DataError:
        return first
    return second if len(second[2]) < len(first[2]) else first


def _pick_matcher(config: ProcessConfig, is_video: bool, n_images: int) -> str:
    if config.matcher != "auto":
        return config.matcher
    return "sequential" if is_video or n_images > EXHAUSTIVE_MAX else "exhaustive"


def _build(source: Path, tmp: Path, config: ProcessConfig, report: dict) -> None:
    """Every stage, writing into the temporary scene folder ``tmp``; fills ``report``."""
    from ngp_warp.data.colmap import colmap_to_transforms, read_colmap_model

    clock = time.perf_counter()
    sizes, is_video = gather_photos(source, tmp / "images", config.frames, config.fps, config.show_progress)
    if len(sizes) < MIN_REGISTERED:
        raise DataError(f"{source}: {len(sizes)} image(s); structure from motion needs at least {MIN_REGISTERED}")
    masks = None if config.masks is None else gather_masks(Path(config.masks), sizes, tmp)
    report["seconds"]["frames" if is_video else "copy"] = time.perf_counter() - clock
    matcher = _pick_matcher(config, is_video, len(sizes))
    work = tmp / ".sfm"
    work.mkdir()
    clock = time.perf_counter()
    database, report["sift_device"] = _features_and_matches(work, tmp / "images", sizes, matcher, config, masks)
    report["seconds"]["features+matching"] = time.perf_counter() - clock
    clock = time.perf_counter()
    model, report["mapper"], report["contradicted"] = _sound_mapping(work, database, tmp / "images", len(sizes),
                                                                      config)
    report["seconds"]["mapping"] = time.perf_counter() - clock
    sparse = tmp / "sparse" / "0"
    sparse.mkdir(parents=True)
    model.write(sparse)
    shutil.rmtree(work)
    meta = colmap_to_transforms(read_colmap_model(sparse), image_dir_rel="images")
    if masks is not None:
        name_masks(meta)
    (tmp / "transforms.json").write_text(json.dumps(meta, indent=2))
    report.update(registered=model.num_reg_images(), total=len(sizes), matcher=matcher,
                  mean_reprojection_error=float(model.compute_mean_reprojection_error()))


def process(source: str | Path, scene_dir: str | Path, config: ProcessConfig | None = None) -> ProcessReport:
    """Pose the photos in folder ``source`` (or frames of the video ``source``) and write ``scene_dir``.

    Returns:
        The :class:`ProcessReport`.

    Raises:
        DataError: pycolmap missing, bad input (no such path, no images, a file that is no
            video, an unreadable image, photos of more than one size, fewer than 3 images),
            ``scene_dir`` exists (without ``config.overwrite``), fewer than 3 images registered,
            the model split in parts, or masks that do not fit
            (:func:`~ngp_warp.data.process_masks.check_masks`,
            :func:`~ngp_warp.data.process_masks.gather_masks`). Nothing is left in ``scene_dir``'s
            place then.
    """
    from ngp_warp.atomic import atomic_dir

    config = config or ProcessConfig()
    config.check()
    require_pycolmap()
    source, out = Path(source), Path(scene_dir)
    if out.exists() and not config.overwrite:
        raise DataError(f"{out}: already exists (choose another folder or pass --overwrite)")
    if out.resolve() == source.resolve() or out.resolve() in source.resolve().parents:
        raise DataError(f"{out}: the scene folder cannot hold its own input {source}")
    if config.masks is not None:
        check_masks(Path(config.masks), source, out)
    created = [p for p in [out.parent, *out.parent.parents] if not p.exists()]
    report, start = {"seconds": {}}, time.perf_counter()
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with atomic_dir(out) as tmp:
            _build(source, tmp, config, report)
    except OSError as e:
        raise DataError(f"{out}: cannot write the scene ({e.strerror or e})") from None
    finally:
        if not out.exists():
            for p in created:  # innermost first; stops at the first that is not empty
                try:
                    p.rmdir()
                except OSError:
                    break
    report["seconds"]["total"] = time.perf_counter() - start
    return ProcessReport(scene=out, **report)
