"""Where a scene's frames come from, before any pixel is read: its transforms file(s) or its
COLMAP model, and the image files they name. Imports neither torch nor Warp, so that a command
can start decoding a scene's images while torch imports (:mod:`ngp_warp.data.prefetch`)."""

from __future__ import annotations

from pathlib import Path

from ngp_warp.data.colmap import colmap_to_transforms, read_colmap_model
from ngp_warp.data.data_error import DataError
from ngp_warp.data.transforms_json import read_frames, read_json


def _colmap_sparse(folder: Path) -> Path | None:
    for sparse in (folder / "sparse" / "0", folder / "sparse"):
        if any((sparse / f"cameras{ext}").is_file() for ext in (".bin", ".txt")):
            return sparse
    return None


def scene_sources(path: Path, downscale: int) -> tuple[list[tuple[dict, Path, Path]], str, int]:
    """([(meta, source for messages, image base)] for train (and test), kind, downscale left to apply)."""
    if path.is_file():
        return [(read_json(path), path, path.parent)], "json", downscale
    if not path.is_dir():
        raise DataError(f"{path}: no such file or folder")
    if (path / "transforms_train.json").is_file():
        test = path / "transforms_test.json"
        if test.exists() and not test.is_file():
            raise DataError(f"{test}: is not a file (a test split must be a transforms file)")
        jsons = [path / "transforms_train.json"] + [test] * test.exists()
        return [(read_json(p), p, path) for p in jsons], "json", downscale
    if (path / "transforms.json").is_file():
        return [(read_json(path / "transforms.json"), path / "transforms.json", path)], "json", downscale
    sparse = _colmap_sparse(path)
    if sparse is None:
        raise DataError(f"{path}: no transforms_train.json, transforms.json or COLMAP sparse/0/ in this folder")
    image_dir = f"images_{downscale}"
    if downscale == 1 or not (path / image_dir).is_dir():
        image_dir = "images"
    if not (path / image_dir).is_dir():
        raise DataError(f"{path}: no {image_dir}/ folder beside the COLMAP model in {sparse.relative_to(path)}/")
    meta = colmap_to_transforms(read_colmap_model(sparse), image_dir)
    return [(meta, sparse, path)], "colmap", 1 if image_dir != "images" else downscale


def scene_image_files(path: Path, downscale: int) -> list[Path]:
    """Every image file that :func:`~ngp_warp.data.loading.load_scene` reads for the scene at
    ``path`` at ``downscale`` (its train and test frames); DataError where it would raise one."""
    return [frame.image for source in scene_sources(path, downscale)[0] for frame in read_frames(*source)]
