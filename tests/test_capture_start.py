"""A bounded capture's start on CUDA (``capture_start``): a learning-rate warm-up, an open occupancy
grid and seen-only refreshes lasting until the batches have met a share of the training pixels;
a capture whose share takes no more than the usual warm-up starts as every other run."""

import dataclasses
from types import SimpleNamespace

import pytest
import torch

from ngp_warp.data.loading import load_scene
from ngp_warp.data.scene_unbounded import write_unbounded_scene
from ngp_warp.training.checkpoint import _train_config
from ngp_warp.training.config import TrainConfig, resolve_defaults
from ngp_warp.training.scene_defaults import (CAPTURE_WARMUP_STEPS, NOMINAL_SAMPLES_PER_RAY, START_PIXEL_SHARE,
                                              WARMUP_STEPS, capture_start)

USUAL_START = (WARMUP_STEPS, 0, False)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return load_scene(write_unbounded_scene(tmp_path_factory.mktemp("u") / "u", width=8, height=8, n_train=12, n_test=2))


def _sized(n: int, height: int, width: int, source: str = "colmap"):
    """A scene of ``n`` training images of ``height`` × ``width``: all that the rule reads."""
    return SimpleNamespace(source=source, train=SimpleNamespace(images=torch.zeros(n, height, width, 3, dtype=torch.uint8)))


@pytest.mark.parametrize("n, height, width", [(43, 1920, 1080), (131, 400, 400), (52, 100, 100), (300, 100, 100)])
def test_the_start_lasts_until_the_batches_have_met_a_share_of_the_pixels(n, height, width):
    samples, subrays = 1 << 18, 4
    steps = START_PIXEL_SHARE * n * height * width / (samples / (subrays * NOMINAL_SAMPLES_PER_RAY))
    start = capture_start(_sized(n, height, width), None, "cuda", samples, subrays)
    if steps <= WARMUP_STEPS:  # small images: every other run's start
        assert start == USUAL_START
    else:
        expected = min(round(steps), CAPTURE_WARMUP_STEPS)
        assert start == (expected, expected, True)
    assert (start[0] == CAPTURE_WARMUP_STEPS) == ((n, height) == (43, 1920))  # fox's size takes the longest


def test_other_runs_start_as_main():
    fox = _sized(43, 1920, 1080)
    assert capture_start(fox, None, "cuda", 1 << 18, 4)[0] == CAPTURE_WARMUP_STEPS
    assert capture_start(fox, "l2", "cuda", 1 << 18, 4) == USUAL_START  # contracted
    assert capture_start(fox, None, "cpu", 1 << 15, 1) == USUAL_START  # the CPU
    assert capture_start(_sized(43, 1920, 1080, "nerf-synthetic"), None, "cuda", 1 << 18, 4) == USUAL_START
    # more samples a step meet more pixels: the same share in fewer steps
    assert capture_start(_sized(131, 400, 400), None, "cuda", 1 << 19, 4)[0] < \
        capture_start(_sized(131, 400, 400), None, "cuda", 1 << 18, 4)[0]


def test_a_step_budget_holds_the_start_to_a_tenth_of_it():
    fox = _sized(43, 1920, 1080)
    assert capture_start(fox, None, "cuda", 1 << 18, 4, budget_steps=1500) == (150, 150, True)
    assert capture_start(fox, None, "cuda", 1 << 18, 4, budget_steps=900) == USUAL_START  # a tenth is under the usual 100
    assert capture_start(fox, None, "cuda", 1 << 18, 4, budget_steps=20_000)[0] == CAPTURE_WARMUP_STEPS


# 12 images of 8 × 8 at 16 samples a step of 2 × 2 sub-rays: 0.25 pixels a step, 154 steps to meet 5 %
TINY_BATCHES = dict(contraction=None, target_samples=16, supersample=2)


def test_resolved_settings_and_what_the_user_sets(capture):
    steps = round(START_PIXEL_SHARE * 12 * 8 * 8 * 4 * NOMINAL_SAMPLES_PER_RAY / 16)
    assert WARMUP_STEPS < steps < CAPTURE_WARMUP_STEPS
    resolved = resolve_defaults(TrainConfig(**TINY_BATCHES), capture, "cuda")
    assert (resolved.lr_warmup, resolved.occupancy_open_steps, resolved.grid_seen_only) == (steps, steps, True)
    resolved = resolve_defaults(TrainConfig(**TINY_BATCHES), capture, "cpu")
    assert (resolved.lr_warmup, resolved.occupancy_open_steps, resolved.grid_seen_only) == USUAL_START
    asked = TrainConfig(**TINY_BATCHES, lr_warmup=300, occupancy_open_steps=0, grid_seen_only=False)
    resolved = resolve_defaults(asked, capture, "cuda")
    assert (resolved.lr_warmup, resolved.occupancy_open_steps, resolved.grid_seen_only) == (300, 0, False)


def test_a_checkpoint_without_the_start_settings_trained_with_mains(capture):
    saved = dataclasses.asdict(resolve_defaults(TrainConfig(**TINY_BATCHES), capture, "cuda"))
    assert saved["grid_seen_only"]
    for key in ("lr_warmup", "occupancy_open_steps", "grid_seen_only"):
        del saved[key]
    config = _train_config("ck.pt", saved, 0.1)
    assert (config.lr_warmup, config.occupancy_open_steps, config.grid_seen_only) == USUAL_START
