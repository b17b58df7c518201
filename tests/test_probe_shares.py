"""benchmarks/probe_shares.py: one probe's shares at each mark, on a small sky capture."""

from ngp_warp.data.loading import load_scene
from ngp_warp.data.scene import write_demo_scene
from ngp_warp.training.config import TrainConfig, cpu_sizes

from benchmark_scripts import load_benchmark


def test_probe_shares_reads_both_shares_at_each_mark(tmp_path, capsys):
    probe_shares, capture_scenes = load_benchmark("probe_shares"), load_benchmark("capture_scenes")
    demo = write_demo_scene(tmp_path / "demo", width=24, height=24, n_train=10, n_test=2, supersample=1)
    sky = capture_scenes.write_capture(demo, tmp_path / "sky", "colmap-sky")
    config = cpu_sizes(TrainConfig())
    config.target_samples, config.grid_resolution = 1 << 10, 16
    config.field.log2_hashmap_size, config.field.n_levels, config.field.hidden = 12, 4, 16
    rows = probe_shares.probe_shares(load_scene(sky), 3, [10, 20], 600.0, "cpu", config)
    assert (config.seed, config.seconds, config.contraction_fit) == (0, None, "auto")  # the caller's config untouched
    assert [r["step"] for r in rows] == [10, 20] and all(r["seed"] == 3 for r in rows)
    for r in rows:
        assert 0.0 <= r["share"] <= 1.0 and 0.0 <= r["cells"] <= 1.0 and r["score"] == r["share"] + r["cells"]
    assert 0 < rows[0]["seconds"] < rows[1]["seconds"]
