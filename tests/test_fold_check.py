"""The check of a model against its own matches (ngp_warp.data.fold_check) and process's second
mapping when a model fails it, on cameras in a ring whose neighbours share matches."""

import math

import numpy as np
import pytest

from ngp_warp.data import process as P
from ngp_warp.data.data_error import DataError
from ngp_warp.data.fold_check import FOLD_ANGLE, MIN_INLIERS, contradicted_images


def ring(n=36):
    """Optical axes of n cameras in a ring looking at its centre, {name: axis}, and the matches
    of a walk around it: each image shares 150 or 200 verified matches with each neighbour (no
    ties), 60 with the next ones, and 5 (below MIN_INLIERS) with the view opposite."""
    angles = 2 * math.pi * np.arange(n) / n
    axes = {f"{i:03d}": -np.array([math.cos(a), math.sin(a), 0.2]) for i, a in enumerate(angles)}
    inliers = {}
    for i in range(n):
        inliers[f"{i:03d}", f"{(i + 1) % n:03d}"] = 150 + 50 * (i % 2)
        inliers[f"{i:03d}", f"{(i + 2) % n:03d}"] = 60
        inliers[f"{i:03d}", f"{(i + n // 2) % n:03d}"] = 5
    return axes, inliers


def folded(axes, names):
    """The axes with the cameras ``names`` turned by 180° about the ring's axis (z): the back of
    the subject posed as its front."""
    turn = np.diag([-1.0, -1.0, 1.0])
    return {name: turn @ axis if name in names else axis for name, axis in axes.items()}


def test_a_sound_ring_has_no_contradicted_image():
    axes, inliers = ring()
    assert contradicted_images(axes, inliers) == []


def test_a_folded_ring_names_the_images_at_the_fold():
    axes, inliers = ring()
    back = {f"{i:03d}" for i in range(10, 28)}  # half the ring, turned onto the other half
    flagged = contradicted_images(folded(axes, back), inliers)
    # the images on either side of the fold's two seams; the turned images inside agree with
    # each other, the kept ones too
    assert flagged == ["009", "010", "027", "028"]
    assert contradicted_images(folded(axes, back), inliers, max_angle=179.0) == []  # the limit is the angle


def test_weak_pairs_and_unposed_images_are_ignored():
    axes, inliers = ring()
    back = {f"{i:03d}" for i in range(10, 28)}
    weak = {pair: MIN_INLIERS - 1 for pair in inliers}
    assert contradicted_images(folded(axes, back), weak) == []
    unposed = {name: axis for name, axis in folded(axes, back).items() if name not in {"009", "010"}}
    assert contradicted_images(unposed, inliers) == ["027", "028"]


def test_an_image_whose_best_match_lies_just_inside_the_angle_passes():
    a = np.array([1.0, 0.0, 0.0])
    near = np.array([math.cos(math.radians(FOLD_ANGLE - 1)), math.sin(math.radians(FOLD_ANGLE - 1)), 0.0])
    far = np.array([math.cos(math.radians(FOLD_ANGLE + 1)), math.sin(math.radians(FOLD_ANGLE + 1)), 0.0])
    assert contradicted_images({"a": a, "b": near}, {("a", "b"): 100}) == []
    assert contradicted_images({"a": a, "b": far}, {("b", "a"): 100}) == ["a", "b"]


@pytest.fixture
def two_mappers(monkeypatch):
    """process's mapping with each mapper's model replaced by a name, and the check by a table
    of contradicted images per mapper; returns the mappers called, in order."""
    calls = []
    outcome = {}

    def mapping(work, database, images_dir, n_images, show, mapper):
        calls.append(mapper)
        if isinstance(outcome[mapper], Exception):
            raise outcome[mapper]
        return mapper

    monkeypatch.setattr(P, "_mapping", mapping)
    monkeypatch.setattr("ngp_warp.data.fold_check.model_axes", lambda model: model)
    monkeypatch.setattr("ngp_warp.data.fold_check.database_inliers", lambda database, model: model)
    monkeypatch.setattr("ngp_warp.data.fold_check.contradicted_images", lambda axes, inliers: outcome[axes])
    return calls, outcome


def test_a_sound_model_is_mapped_once(two_mappers):
    calls, outcome = two_mappers
    outcome["global"] = []
    model, mapper, contradicted = P._sound_mapping(None, None, None, 40, P.ProcessConfig(show_progress=False))
    assert (model, mapper, contradicted, calls) == ("global", "global", [], ["global"])


def test_a_contradicted_model_is_mapped_again_by_the_other_mapper(two_mappers):
    calls, outcome = two_mappers
    outcome.update({"global": ["a", "b"], "incremental": []})
    assert P._sound_mapping(None, None, None, 40, P.ProcessConfig(show_progress=False))[1:] == ("incremental", [])
    assert calls == ["global", "incremental"]
    outcome.update({"global": ["a"], "incremental": ["a", "b"]})  # the other is worse: the first stays
    assert P._sound_mapping(None, None, None, 40, P.ProcessConfig(show_progress=False))[1:] == ("global", ["a"])
    outcome.update({"global": ["a"], "incremental": DataError("split")})  # the other fails: the first stays
    assert P._sound_mapping(None, None, None, 40, P.ProcessConfig(show_progress=False))[1:] == ("global", ["a"])
    outcome.update({"incremental": ["a"], "global": []})
    config = P.ProcessConfig(mapper="incremental", show_progress=False)
    assert P._sound_mapping(None, None, None, 40, config)[1:] == ("global", [])
