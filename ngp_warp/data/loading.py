"""Scenes on disk: NeRF-synthetic folders, instant-ngp ``transforms.json`` and COLMAP models.

* NeRF-synthetic and instant-ngp files: see :mod:`ngp_warp.data.transforms_json` (frames whose image
  is missing are skipped with one warning, as instant-ngp does).
* The image files, read on threads and downscaled: :mod:`ngp_warp.data.images`.
* COLMAP: a folder with ``sparse/0/`` (or ``sparse/``) holding ``cameras``, ``images`` and
  ``points3D`` (.bin or .txt) and the images in ``images/`` (``images_N/`` with downscale N when
  that folder exists, as in the mip-NeRF 360 and nerfstudio layouts). The model becomes an
  instant-ngp transforms dict (:func:`ngp_warp.data.colmap.colmap_to_transforms`): OpenGL axes, up
  +z, centred and scaled (:mod:`ngp_warp.data.scene_normalisation`); ``Scene.world_from_scene`` maps
  the scene back to COLMAP's frame and :func:`write_normalisation` records it in a run.

Every problem with the files raises :class:`DataError`, one line naming the file and the problem.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ngp_warp.atomic import atomic_write_text
from ngp_warp.data.cameras import LENS_FISHEYE, LENS_OPENCV, LENS_PINHOLE, generate_rays
from ngp_warp.data.data_error import DataError, short
from ngp_warp.data.images import downscale_image, load_images, load_masks
from ngp_warp.data.prefetch import collect_prefetched, read_prefetched
from ngp_warp.data.scene_sources import scene_sources
from ngp_warp.data.transforms_json import (NGP_SCENE_KEYS, Frame, check_pose_set, contraction_key, declared_size, frame_camera, log,
                                      named_split, read_frames, world_box, world_from_scene)

__all__ = ["DataError", "Split", "Scene", "load_scene", "generate_rays", "image_rays", "downscale_image",
           "normalisation_record", "write_normalisation"]

NERF_SYNTHETIC_BOUND = 1.5
NEAR_IN_UNIT_CUBE = 0.1  # near distance, in instant-ngp unit-cube lengths
NORMALISATION_FILE = "normalisation.json"


@dataclass
class Split:
    """The images and cameras of one split.

    Attributes:
        images: [N, H, W, C] uint8, C = 3 (RGB) or 4 (RGBA, straight alpha).
        c2w: [N, 3, 4] float32 camera-to-world, OpenGL convention (camera looks down -z, +y up).
        intrinsics: [N, 4] float32 fx, fy, cx, cy in pixels of ``images``.
        distortion: [N, 6] float32 k1, k2, k3, k4, p1, p2 (zeros when none): OpenCV's
            radial-tangential model (k4 = 0), or with ``fisheye`` OpenCV's fisheye (p1 = p2 = 0).
        names: N image file paths.
        width, height: W and H.
        fisheye: the cameras are OpenCV fisheye (equidistant) lenses.
        masks: [N, H, W] bool, the pixels to train on (the frames' masks, ``Frame.mask``), or None: all.
        has_distortion: any distortion coefficient is non-zero, or fisheye (computed; pass
            ``distortion`` to :func:`generate_rays` only then).
    """

    images: torch.Tensor
    c2w: torch.Tensor
    intrinsics: torch.Tensor
    distortion: torch.Tensor
    names: list[str]
    width: int
    height: int
    fisheye: bool = False
    masks: torch.Tensor | None = None
    has_distortion: bool = field(init=False)

    def __post_init__(self):
        n = len(self.names)
        expect = {
            "images": (self.images, (n, self.height, self.width, None), torch.uint8),
            "c2w": (self.c2w, (n, 3, 4), torch.float32),
            "intrinsics": (self.intrinsics, (n, 4), torch.float32),
            "distortion": (self.distortion, (n, 6), torch.float32),
        }
        if self.masks is not None:
            expect["masks"] = (self.masks, (n, self.height, self.width), torch.bool)
        for name, (t, shape, dtype) in expect.items():
            if t.dim() != len(shape) or any(s is not None and s != d for s, d in zip(shape, t.shape)):
                raise ValueError(f"Split.{name} has shape {list(t.shape)}, expected {list(shape)}")
            if t.dtype != dtype:
                raise ValueError(f"Split.{name} must be {dtype}, got {t.dtype}")
        if self.images.shape[-1] not in (3, 4):
            raise ValueError(f"Split.images must have 3 or 4 channels, got {self.images.shape[-1]}")
        self.has_distortion = self.fisheye or bool((self.distortion != 0).any())

    def __len__(self) -> int:
        return len(self.names)

    @property
    def lens_model(self) -> int:
        """The ray kernel's lens code: LENS_PINHOLE, LENS_OPENCV or LENS_FISHEYE."""
        return LENS_FISHEYE if self.fisheye else LENS_OPENCV if self.has_distortion else LENS_PINHOLE

    def camera(self, i: int) -> dict:
        """View ``i``'s camera as the renderer's keywords (``Trainer.render_image``,
        ``fit_appearance_code``): c2w [3, 4], intrinsics [4] float32, width, height, distortion
        [6] float32 or None (no distortion), fisheye."""
        return dict(c2w=self.c2w[i], intrinsics=self.intrinsics[i], width=self.width, height=self.height,
                    distortion=self.distortion[i] if self.has_distortion else None, fisheye=self.fisheye)

    def to(self, device) -> "Split":
        return Split(self.images.to(device), self.c2w.to(device), self.intrinsics.to(device),
                     self.distortion.to(device), list(self.names), self.width, self.height, self.fisheye,
                     None if self.masks is None else self.masks.to(device))

    def rays(self, image_index: torch.Tensor, px: torch.Tensor, py: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Rays through pixels (px[b], py[b]) of images image_index[b] (all [B] int, on the
        split's device) -> rays_o [B, 3], rays_d [B, 3] unit; see :func:`generate_rays`."""
        dist = self.distortion[image_index] if self.has_distortion else None
        return generate_rays(self.c2w[image_index], self.intrinsics[image_index], dist, px, py, fisheye=self.fisheye)


@dataclass
class Scene:
    """A loaded scene.

    Attributes:
        train, test: the training and evaluation splits.
        test_is_heldout: the folder had no test split; ``test`` holds every
            ``holdout_every``-th frame, removed from ``train``.
        aabb: [6] float32 xmin, ymin, zmin, xmax, ymax, zmax of the box the field lives in (scene).
        occupancy_levels: cascades that box needs: 1 + ceil(log2(aabb_scale)), at least 1.
        near: near distance for rays (scene units).
        source: "nerf-synthetic", "instant-ngp" or "colmap".
        occupancy_aabb: [6] float32, the finest cascade's box: instant-ngp's unit cube in the
            scene; cascade k covers it scaled by 2^k about its centre, the last one covers
            ``aabb``. Equal to ``aabb`` when there is one level (defaults to it).
        world_from_scene: [4, 4] float64 similarity from the scene's frame to the capture's
            (COLMAP's world for COLMAP scenes): world point = M @ (scene point, 1). Identity
            (the default) when the files are already in their own world frame.
        contraction: the scene contraction the files ask for (``"l2"``, ``"linf"``; the
            ``contraction`` key), else None (see :mod:`ngp_warp.contraction_choice`).
    """

    train: Split
    test: Split
    test_is_heldout: bool
    aabb: torch.Tensor
    occupancy_levels: int
    near: float
    source: str
    occupancy_aabb: torch.Tensor | None = None
    world_from_scene: torch.Tensor | None = None
    contraction: str | None = None

    def __post_init__(self):
        if self.occupancy_aabb is None:
            self.occupancy_aabb = self.aabb.clone()
        if self.world_from_scene is None:
            self.world_from_scene = torch.eye(4, dtype=torch.float64)

    def with_aabb_scale(self, aabb_scale: int | None) -> "Scene":
        """This scene with the field's box ``aabb_scale`` times the finest cascade's box (about
        its centre, instant-ngp's ``aabb_scale``; a power of two) and the cascades it needs;
        itself for None."""
        if aabb_scale is None:
            return self
        box = self.occupancy_aabb
        centre, half = (box[:3] + box[3:]) / 2, (box[3:] - box[:3]) / 2 * aabb_scale
        return dataclasses.replace(self, aabb=torch.cat([centre - half, centre + half]),
                                   occupancy_levels=1 + int(math.log2(aabb_scale)))


def normalisation_record(scene: Scene) -> dict:
    """JSON-able record of how ``scene`` maps back to the capture's frame: ``world_from_scene``
    [4, 4] (world point = M @ (scene point, 1)), its ``scale`` (world length per scene length)
    and the scene's ``source``."""
    m = scene.world_from_scene.double()
    return {"world_from_scene": m.tolist(), "scale": float(torch.linalg.det(m[:3, :3]) ** (1 / 3)),
            "source": scene.source}


def write_normalisation(run_dir: str | Path, scene: Scene) -> Path:
    """Write :func:`normalisation_record` to ``run_dir/normalisation.json`` (atomically); returns its path."""
    path = Path(run_dir) / NORMALISATION_FILE
    atomic_write_text(path, json.dumps(normalisation_record(scene), indent=2) + "\n")
    return path


def image_rays(split: Split, index: int) -> tuple[torch.Tensor, torch.Tensor]:
    """All rays of image ``index`` of ``split``, row-major: rays_o, rays_d [H * W, 3] float32."""
    if not 0 <= index < len(split):
        raise ValueError(f"image index {index} out of range for a split of {len(split)} images")
    dev = split.c2w.device
    ys, xs = torch.meshgrid(torch.arange(split.height, device=dev), torch.arange(split.width, device=dev),
                            indexing="ij")
    idx = torch.full((split.height * split.width,), index, device=dev, dtype=torch.long)
    return split.rays(idx, xs.reshape(-1), ys.reshape(-1))


def _warn_rescaled(frames: list[Frame], sizes: list[tuple[int, int]]) -> None:
    """One warning when frames declare a w x h other than their image's (same aspect ratio)."""
    odd = [(f, size) for f, size in zip(frames, sizes) if declared_size(f) not in (None, size)]
    if odd:
        (frame, (w, h)), declared = odd[0], declared_size(odd[0][0])
        log.warning(f"ngp-warp: {frame.where}: w x h = {declared[0]:g}x{declared[1]:g} but the image is {w}x{h}; "
                    f"focal length and centre scaled to the image ({len(odd)} of {len(frames)} frames)")


def _split(frames: list[Frame], images: np.ndarray, sizes: list[tuple[int, int]], downscale: int,
           masks: np.ndarray | None = None) -> Split:
    intr, dist, fisheye = zip(*(frame_camera(f, w, h) for f, (w, h) in zip(frames, sizes)))
    _warn_rescaled(frames, sizes)
    if len(set(fisheye)) > 1:
        odd = frames[fisheye.index(not fisheye[0])]
        raise DataError(f"{odd.where}: mixes fisheye and perspective cameras in one split (one lens model per scene)")
    intrinsics = torch.tensor(intr, dtype=torch.float64) / downscale
    return Split(
        images=torch.from_numpy(images),
        c2w=torch.from_numpy(np.stack([f.c2w for f in frames])).float(),
        intrinsics=intrinsics.float(),
        distortion=torch.tensor(dist, dtype=torch.float32),
        names=[str(f.image) for f in frames],
        width=images.shape[2],
        height=images.shape[1],
        fisheye=fisheye[0],
        masks=None if masks is None else torch.from_numpy(masks),
    )


def load_scene(path: str | Path, downscale: int = 1, holdout_every: int = 8) -> Scene:
    """Load a NeRF-synthetic folder, an instant-ngp ``transforms.json`` (folder or file) or a
    COLMAP folder (``sparse/0/`` + ``images/``).

    Args:
        path: folder with ``transforms_train.json`` (and optionally ``transforms_test.json``),
            folder with ``transforms.json``, the path of a transforms file, or a COLMAP folder.
        downscale: integer factor; images are area-averaged over n x n blocks (cropped to a
            multiple of n) and the intrinsics divided by n. A COLMAP folder's ``images_n/``,
            when there, is read as it is instead.
        holdout_every: without a test split (a transforms_test.json, or nerfstudio's
            ``test_filenames`` / ``val_filenames`` lists), frames 0, k, 2k, ... (sorted by file
            name) become the test split and leave training.

    Returns:
        The :class:`Scene`; images stay uint8 on the CPU.

    Raises:
        DataError: any problem with the files, in one line naming the file.
    """
    path = Path(path)
    if isinstance(downscale, bool) or not isinstance(downscale, int) or downscale < 1:
        raise DataError(f"downscale must be a positive integer, got {short(downscale)}")
    if isinstance(holdout_every, bool) or not isinstance(holdout_every, int) or holdout_every < 2:
        raise DataError(f"holdout_every must be an integer of at least 2, got {short(holdout_every)}")
    sources, kind, downscale = scene_sources(path, downscale)
    metas = [meta for meta, _, _ in sources]
    train = read_frames(*sources[0])
    named = None if len(sources) > 1 else named_split(metas[0], train, sources[0][1], sources[0][2])
    if len(sources) > 1:
        test = read_frames(*sources[1])
    elif named is not None:  # nerfstudio's test_filenames / val_filenames (and train_filenames)
        train, test = named
    else:
        if len(train) < 2:
            raise DataError(f"{sources[0][1]}: only 1 frame; at least 2 are needed to hold out test frames")
        test = train[::holdout_every]
        train = [f for k, f in enumerate(train) if k % holdout_every]

    for frames in (train, train + test):  # the training views apart, then beside the test views
        check_pose_set(frames, sources[0][1])
    collect_prefetched()  # here, not on a loader thread: a Ctrl-C while the child finishes ends it
    images, sizes = load_images(train + test, downscale, read=read_prefetched)
    n = len(train)
    first = sources[0][1]
    is_ngp = kind == "colmap" or first.name != "transforms_train.json" or any(
        k in m for m in metas for k in NGP_SCENE_KEYS)
    if is_ngp:
        aabb, cascade_box, levels, scale = world_box(metas[0], first)
    else:
        b = NERF_SYNTHETIC_BOUND
        aabb, levels, scale = [-b, -b, -b, b, b, b], 1, 0.5 / b
        cascade_box = aabb
    return Scene(
        train=_split(train, images[:n], sizes[:n], downscale, load_masks(train, sizes[:n], downscale)),
        test=_split(test, images[n:], sizes[n:], downscale),
        test_is_heldout=len(sources) == 1 and named is None,
        aabb=torch.tensor(aabb, dtype=torch.float32),
        occupancy_levels=levels,
        near=round(NEAR_IN_UNIT_CUBE / scale, 6),
        source=kind if kind == "colmap" else "instant-ngp" if is_ngp else "nerf-synthetic",
        occupancy_aabb=torch.tensor(cascade_box, dtype=torch.float32),
        world_from_scene=torch.from_numpy(world_from_scene(metas[0], first)),
        contraction=contraction_key(metas[0], first),
    )
