"""benchmarks/bench_march_schedule.py's schedule parsing and its count of rays whose samples differ."""

import argparse

import pytest
import torch

from ngp_warp.ops.march_schedule import MarchSchedule

from benchmark_scripts import load_benchmark

bench = load_benchmark("bench_march_schedule")


def test_schedules_parse_with_and_without_a_thread_bound_and_mask_words():
    assert bench.schedule("32:128") == MarchSchedule(32, 128)
    assert bench.schedule("32:128:4194304") == MarchSchedule(32, 128, 4194304)
    assert bench.schedule("32:128:4194304/0") == MarchSchedule(32, 128, 4194304, mask_words=0)
    assert bench.schedule("512:8/16") == MarchSchedule(512, 8, mask_words=16)
    for bad in ("32", "32:0", "1:2:3:4", "32:128/-1", "32:128/x"):
        with pytest.raises(argparse.ArgumentTypeError):
            bench.schedule(bad)


def test_rays_that_differ_count_samples_and_their_distances():
    offsets = torch.tensor([0, 2, 3, 5])  # three rays of 2, 1 and 2 samples
    rays = torch.tensor([0, 0, 1, 2, 2])
    t = torch.tensor([0.1, 0.2, 0.5, 0.3, 0.4])
    assert bench.rays_that_differ((offsets, rays, t), (offsets, rays, t.clone())) == 0
    moved = t.clone()
    moved[3] += 1e-6  # ray 2's first sample
    assert bench.rays_that_differ((offsets, rays, t), (offsets, rays, moved)) == 1
    one_more = (torch.tensor([0, 2, 4, 6]), torch.tensor([0, 0, 1, 1, 2, 2]), torch.tensor([0.1, 0.2, 0.5, 0.6, 0.3, 0.4]))
    assert bench.rays_that_differ((offsets, rays, t), one_more) == 1  # ray 1 has a sample more
    both = (one_more[0], one_more[1], torch.tensor([0.1, 0.2, 0.5, 0.6, 0.3, 0.45]))
    assert bench.rays_that_differ((offsets, rays, t), both) == 2  # and ray 2, behind it, a sample moved
