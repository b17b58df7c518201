"""Poses that contradict their own matches: the check ``process`` runs on every model.

Structure from motion can fold a model along a symmetry of the subject: the views of an
object's back are posed as if they saw its front. The folded model is self-consistent enough
to look like a success (every image registered, a sub-pixel reprojection error), but it
contradicts the images' own matches: an image shares the most verified matches with the view
taken beside it, and a folded image's best-matched view then sits on the other side of the
object. Views that far apart cannot share many matches (SIFT, even with affine shapes, stops
matching long before 60° of viewpoint change), so an image whose most-matched image lies more
than :data:`FOLD_ANGLE` away (the angle between their optical axes) is contradicted.

Measured on 40 of lego's views over white (2 CPU cores, benchmarks/RESULTS.md): in a right model
every image's best match lies within 29° (the true angles: the same); in a folded one four
images were turned by 179–180°, and each of those whose best match stayed unfolded was flagged
(113–142°).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

FOLD_ANGLE = 60.0  # degrees between an image's optical axis and its most-matched image's
MIN_INLIERS = 15  # verified matches that make a pair count: COLMAP's default minimum (process verifies
                  # with data.process.VERIFY_MIN_INLIERS, so every pair it stores passes)


def contradicted_images(axes: dict[str, np.ndarray], inliers: dict[tuple[str, str], int],
                        max_angle: float = FOLD_ANGLE) -> list[str]:
    """The images whose most-matched image is posed more than ``max_angle`` degrees away.

    Args:
        axes: {image name: [3] float optical axis in world coordinates} of the posed images.
        inliers: {(name, name): verified matches} of image pairs (either order, each pair once);
            pairs with an image not in ``axes`` or fewer than :data:`MIN_INLIERS` are ignored.
        max_angle: degrees.

    Returns:
        The contradicted images' names, sorted.
    """
    best: dict[str, tuple[int, str]] = {}
    for (a, b), count in inliers.items():
        if count < MIN_INLIERS or a not in axes or b not in axes or a == b:
            continue
        for image, other in ((a, b), (b, a)):
            if count > best.get(image, (0, ""))[0]:
                best[image] = (count, other)
    limit = np.cos(np.radians(max_angle))
    unit = {name: np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis) for name, axis in axes.items()}
    return sorted(image for image, (_, other) in best.items() if float(unit[image] @ unit[other]) < limit)


def model_axes(model) -> dict[str, np.ndarray]:
    """{image name: [3] optical axis in world coordinates} of a pycolmap Reconstruction's posed
    images (a COLMAP camera looks along its +z)."""
    return {image.name: image.cam_from_world().rotation.matrix()[2].copy()
            for image in model.images.values() if image.has_pose}


def database_inliers(database: Path, model) -> dict[tuple[str, str], int]:
    """{(name, name): verified matches} of every image pair in the COLMAP ``database``, named as
    in ``model`` (read through pycolmap's own SQLite, as pycolmap wrote it)."""
    import pycolmap

    names = {image_id: image.name for image_id, image in model.images.items()}
    database_handle = pycolmap.Database.open(str(database))
    try:
        pair_ids, counts = database_handle.read_two_view_geometry_num_inliers()
    finally:
        database_handle.close()
    pairs = {}
    for pair_id, count in zip(pair_ids, counts):
        a, b = pycolmap.pair_id_to_image_pair(pair_id)
        if a in names and b in names:
            pairs[names[a], names[b]] = int(count)
    return pairs
