"""benchmarks/unseen_share.py: the rule zeroes nothing around an object that every camera sees
whole, and something where the cameras stand inside the scene."""

import argparse

from ngp_warp.data.loading import load_scene
from ngp_warp.data.scene import write_demo_scene
from ngp_warp.training.trainer import Trainer

from benchmark_scripts import load_benchmark

unseen_share = load_benchmark("unseen_share")


def test_an_object_seen_whole_loses_nothing_and_a_room_something(tmp_path):
    demo = load_scene(write_demo_scene(tmp_path / "demo", width=24, height=24, n_train=24, n_test=1, supersample=1))
    (label, config), = unseen_share.variants(demo)
    config.grid_resolution = 16
    assert label == "default" and config.grid_seen_only
    share, touched, visible = unseen_share.zeroed_share(Trainer(demo, config, "cpu"), rounds=1)
    assert share == 0.0 and touched == 0 and visible > 0
    args = argparse.Namespace(lego=None, fox=None, downscale=1)
    room = load_scene(unseen_share.bench_captures.scene_folder("room-colmap", tmp_path, args))
    labels = [label for label, _ in unseen_share.variants(room)]
    assert labels == ["probed: contracted", "probed: bounded"]
    config = unseen_share.variants(room)[0][1]
    config.grid_resolution = 16
    share, touched, visible = unseen_share.zeroed_share(Trainer(room, config, "cpu"), rounds=1)
    assert 0.0 < share < 0.1 and 0 < touched < visible
