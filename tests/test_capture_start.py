"""A bounded capture's start on CUDA (``capture_start``): a learning-rate warm-up and an open
occupancy grid lasting until the batches have met a share of the training pixels, and seen-only
refreshes; a capture whose share takes no more than the usual warm-up starts as every other run."""

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


# (images, height, width) → steps of the start at 2^18 samples a step of 2 × 2 sub-rays (4096
# pixels a step): fox's size 1088 steps, held to 1000; 400 × 400 captures 255.9; a round 100
# steps or fewer is the usual start
@pytest.mark.parametrize("n, height, width, steps", [
    (43, 1920, 1080, CAPTURE_WARMUP_STEPS), (131, 400, 400, 256), (101, 256, 320, 101),
    (100, 256, 320, None), (52, 100, 100, None), (300, 100, 100, None)])
def test_the_start_lasts_until_the_batches_have_met_a_share_of_the_pixels(n, height, width, steps):
    start = capture_start(_sized(n, height, width), None, "cuda", 1 << 18, 4)
    assert start == (USUAL_START if steps is None else (steps, steps, True))
    share = START_PIXEL_SHARE * n * height * width / ((1 << 18) / (4 * NOMINAL_SAMPLES_PER_RAY))
    assert steps is None or steps == min(round(share), CAPTURE_WARMUP_STEPS)  # the table above is the rule's


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
    # a step budget holds the start to a tenth of it through the config's own budget
    resolved = resolve_defaults(TrainConfig(**TINY_BATCHES, steps=1300), capture, "cuda")
    assert (resolved.lr_warmup, resolved.occupancy_open_steps, resolved.grid_seen_only) == (130, 130, True)
    resolved = resolve_defaults(TrainConfig(**TINY_BATCHES, steps=1000), capture, "cuda")
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
