"""contraction_fit "probe": the density share inside a contracted grid's inner box, and the probe
that starts again bounded (an object before a distant backdrop) or contracted with the box
holding the cameras, on the budget left."""

import dataclasses
import json
from pathlib import Path

import pytest
import torch

from ngp_warp.cli import main
from ngp_warp.cli.common import UserError, _new_probed_trainer, no_probe, refuse_probe
from ngp_warp.data.loading import load_scene
from ngp_warp.data.scene import write_demo_scene
from ngp_warp.ops.occupancy import OccupancyGrid
from ngp_warp.training import contraction_probe as probe
from ngp_warp.training.config import TrainConfig, cpu_sizes
from ngp_warp.training.scene_defaults import focus_distance
from ngp_warp.training.trainer import Trainer, TrainingDiverged

from benchmark_scripts import load_benchmark

capture_scenes = load_benchmark("capture_scenes")

SMALL = {"target_samples": 1 << 10, "grid_resolution": 16}


def small(**settings) -> TrainConfig:
    """A config of a small batch, grid and field, with ``settings``."""
    config = cpu_sizes(TrainConfig(**settings))
    config.target_samples, config.grid_resolution = SMALL["target_samples"], SMALL["grid_resolution"]
    config.field.log2_hashmap_size, config.field.n_levels, config.field.hidden = 12, 4, 16
    return config


@pytest.fixture(scope="module")
def sky_folder(tmp_path_factory) -> Path:
    """The demo object over the environment at infinity as a COLMAP model: a contracted capture."""
    root = tmp_path_factory.mktemp("probe")
    demo = write_demo_scene(root / "demo", width=24, height=24, n_train=14, n_test=4, supersample=2)
    return capture_scenes.write_capture(demo, root / "sky", "colmap-sky")


@pytest.fixture(scope="module")
def sky(sky_folder):
    return load_scene(sky_folder)


def test_density_share_inside_counts_the_cells_whose_centre_lies_in_the_inner_box():
    grid = OccupancyGrid(torch.tensor([-1.0, -1, -1, 1, 1, 1]), resolution=8, contraction="l2")
    occs = torch.full((8, 8, 8), -1.0)  # cells of 0.5 over [-2, 2]: indices 2..5 lie inside [-1, 1]
    occs[2, 2, 2], occs[5, 3, 4] = 3.0, 1.0  # inside
    occs[6, 3, 3], occs[0, 7, 0] = 4.0, 0.0  # outside (centre x = 1.25; no density)
    grid.occs.copy_(occs.reshape(-1))
    assert probe.density_share_inside(grid) == pytest.approx(0.5)
    grid.occs.fill_(-1.0)
    assert probe.density_share_inside(grid) == 0.0  # nothing seen yet
    with pytest.raises(ValueError, match="contracted grid"):
        probe.density_share_inside(OccupancyGrid(torch.tensor([-1.0, -1, -1, 1, 1, 1]), resolution=8))
    inside = probe.inner_cells(grid).reshape(8, 8, 8)
    assert int(inside.sum()) == 4 ** 3 and inside[2:6, 2:6, 2:6].all()


@pytest.mark.parametrize("threshold, chosen", [(-1.0, "bounded"), (3.0, "cameras")])
def test_the_probe_starts_again_bounded_or_contracted_on_the_budget_left(sky, monkeypatch, threshold, chosen):
    monkeypatch.setattr(probe, "PROBE_STEPS", 6)
    monkeypatch.setattr(probe, "PROBE_MIN_STEPS", 4)
    monkeypatch.setattr(probe, "PROBE_SCORE", threshold)
    monkeypatch.setattr(probe, "PROBE_BUDGET_SHARE", 0.5)
    trainer, seen = probe.probed_trainer(sky, small(steps=12, contraction_fit="probe"), "cpu")
    assert seen.steps == 6 and seen.fit == chosen and trainer.config.contraction_fit == "cameras"
    assert 0.0 <= seen.share <= 1.0 and 0.0 <= seen.cells <= 1.0 and seen.seconds > 0
    assert (trainer.step_count, trainer.config.steps) == (0, 12)  # the new model takes the whole step budget
    assert trainer.train_seconds == pytest.approx(seen.seconds)  # the probe's seconds count
    if chosen == "bounded":  # instant-ngp's cascades in colmap2nerf's box, no contraction, a learned backdrop
        assert trainer.config.contraction is None and trainer.config.aabb_scale == probe.OBJECT_AABB_SCALE == 32
        assert trainer.grid.levels == 6 and trainer.config.field.environment and trainer.field.environment is not None
        assert trainer.model.learns_background
        near = 0.3 * focus_distance(sky.train.c2w)  # a bounded capture's rays start 0.3 of the way to the focus
        assert near > sky.near and trainer.config.near == pytest.approx(near) == trainer.model.march.near
    else:
        inner = Trainer(sky, small(steps=1, contraction_fit="cameras"), device="cpu").grid.inner_aabb_host
        assert trainer.config.contraction == "l2" and trainer.grid.inner_aabb_host == pytest.approx(inner)
        assert trainer.config.near == sky.near  # contracted: the scene's own
        trainer.train(show_progress=False)
        assert trainer.step_count == 12


def test_a_probe_that_finds_an_object_keeps_the_box_and_environment_given(sky, monkeypatch):
    monkeypatch.setattr(probe, "PROBE_STEPS", 4)
    monkeypatch.setattr(probe, "PROBE_MIN_STEPS", 4)
    monkeypatch.setattr(probe, "PROBE_SCORE", -1.0)
    monkeypatch.setattr(probe, "PROBE_BUDGET_SHARE", 0.5)
    config = small(steps=8, contraction_fit="probe", aabb_scale=8)
    config = dataclasses.replace(config, field=dataclasses.replace(config.field, environment=False))
    trainer, seen = probe.probed_trainer(sky, config, "cpu")
    assert seen.fit == "bounded" and trainer.config.aabb_scale == 8 and trainer.grid.levels == 4
    assert trainer.config.field.environment is False and trainer.field.environment is None  # as given


def test_the_probe_counts_every_points_density_and_the_run_keeps_grid_seen_only(sky, monkeypatch):
    monkeypatch.setattr(probe, "PROBE_STEPS", 4)
    monkeypatch.setattr(probe, "PROBE_MIN_STEPS", 4)
    monkeypatch.setattr(probe, "PROBE_BUDGET_SHARE", 0.5)
    made = []

    def make_trainer(scene, config, device):
        made.append((config.grid_seen_only, config.occupancy_open_steps))
        return Trainer(scene, config, device)

    asked = small(steps=8, contraction_fit="probe", grid_seen_only=True, occupancy_open_steps=6)
    trainer, seen = probe.probed_trainer(sky, asked, "cpu", make_trainer=make_trainer)
    # the probe's grid culls as its score was set on; the run keeps what was asked
    assert seen.steps == 4 and made == [(False, 0), (True, 6)] and trainer.grid._seen_frame is not None


@pytest.mark.parametrize("score, steps, chosen", [(-1.0, 10, "bounded"), (3.0, 20, "cameras")])
def test_a_probe_ends_at_the_first_reading_that_tells_an_object(sky, monkeypatch, score, steps, chosen):
    monkeypatch.setattr(probe, "PROBE_STEPS", 20)
    monkeypatch.setattr(probe, "PROBE_READS", (10,))
    monkeypatch.setattr(probe, "PROBE_MIN_STEPS", 4)
    monkeypatch.setattr(probe, "PROBE_SCORE", score)
    monkeypatch.setattr(probe, "PROBE_BUDGET_SHARE", 0.5)
    trainer, seen = probe.probed_trainer(sky, small(steps=40, contraction_fit="probe"), "cpu")
    assert (seen.steps, seen.fit) == (steps, chosen)


def test_shares_inside_count_the_density_and_the_occupied_cells_in_the_inner_box():
    r = 8  # cells of 0.5 over [-2, 2]: indices 2..5 per axis lie inside [-1, 1]
    grid = OccupancyGrid(torch.tensor([-1.0, -1, -1, 1, 1, 1]), resolution=r, contraction="l2")
    occs = torch.full((r ** 3,), -1.0)
    bits = torch.zeros(r ** 3, dtype=torch.bool)

    def cell(i, j, k, density, occupied):
        index = (i * r + j) * r + k
        occs[index], bits[index] = density, occupied

    cell(2, 2, 2, 3.0, True)    # inside
    cell(5, 3, 4, 1.0, False)   # inside, not occupied
    cell(6, 3, 3, 4.0, True)    # outside (x centre 1.25)
    cell(0, 7, 0, 0.0, True)    # outside, no density
    packed = torch.zeros(r ** 3 // 8, dtype=torch.uint8)
    for index in torch.nonzero(bits).flatten().tolist():
        packed[index >> 3] |= 1 << (index & 7)
    grid.occs.copy_(occs)
    grid.bitfield.copy_(packed)
    density, cells = probe.shares_inside(grid)
    assert abs(density - 4.0 / 8.0) < 1e-6
    assert abs(cells - 1.0 / 3.0) < 1e-6


def test_a_probe_out_of_seconds_starts_again_on_the_seconds_left(sky, monkeypatch):
    """A probe of 10^6 steps ends once its steps at the pace of steps 10 to 20 fill its share of
    the budget; the seconds it spent count in the budget of the model trained after it."""
    monkeypatch.setattr(probe, "PROBE_STEPS", 10**6)
    monkeypatch.setattr(probe, "PROBE_MIN_STEPS", 4)
    monkeypatch.setattr(probe, "PACE_FROM", 5)
    monkeypatch.setattr(probe, "PROBE_BUDGET_SHARE", 0.1)
    trainer, seen = probe.probed_trainer(sky, small(seconds=20.0, contraction_fit="probe"), "cpu")
    assert 10 <= seen.steps < 10**4 and seen.share is not None and trainer.step_count == 0
    assert 1.0 <= seen.seconds < 20.0  # about its 2 s (the pace is read at the readouts of steps 10 and 20)
    assert trainer.train_seconds == pytest.approx(seen.seconds)
    assert trainer.config.seconds == pytest.approx(20.0 - seen.seconds)


def test_a_probe_ends_at_its_seconds_after_the_first_step_before_its_pace_is_read(sky, monkeypatch):
    monkeypatch.setattr(probe, "PROBE_STEPS", 10**6)
    monkeypatch.setattr(probe, "PROBE_MIN_STEPS", 10**5)
    monkeypatch.setattr(probe, "PACE_FROM", 10**6)  # no pace read
    monkeypatch.setattr(probe, "PROBE_BUDGET_SHARE", 0.1)
    trainer, seen = probe.probed_trainer(sky, small(seconds=20.0, contraction_fit="probe"), "cpu")
    assert seen.fit == "cameras" and seen.share is None and seen.steps % 10 == 0  # ended at a readout
    assert 2.0 <= seen.seconds < 20.0 and trainer.config.seconds == pytest.approx(20.0 - seen.seconds)


def test_a_probe_whose_first_steps_load_kernels_for_longer_than_its_seconds_runs_its_steps(sky, monkeypatch):
    """With a cold kernel cache the first step compiles for longer than a 60 s run's probe (6.4 s
    on an H100): the probe's seconds count its steps at the pace read after them."""
    step = Trainer.step

    def cold_first_step(self, progress=0.0):
        stats = step(self, progress)
        if self.step_count == 1:
            self.train_seconds += 100.0  # a first step of 100 s against the probe's 60 s
        return stats

    monkeypatch.setattr(Trainer, "step", cold_first_step)
    monkeypatch.setattr(probe, "PROBE_STEPS", 30)
    monkeypatch.setattr(probe, "PROBE_MIN_STEPS", 20)
    monkeypatch.setattr(probe, "PACE_FROM", 10)
    monkeypatch.setattr(probe, "PROBE_BUDGET_SHARE", 0.1)
    trainer, seen = probe.probed_trainer(sky, small(seconds=600.0, contraction_fit="probe"), "cpu")
    assert seen.steps == 30 and seen.share is not None and seen.seconds > 100.0


@pytest.mark.parametrize("probe_steps, min_steps, probed", [(10**5, 10**5, 20), (30, 25, 30)])
def test_a_probe_whose_pace_cannot_reach_its_least_steps_ends_early(sky, monkeypatch, probe_steps, min_steps, probed):
    """The pace read over steps 10 to 20 says whether ``PROBE_MIN_STEPS`` fit in the probe's
    seconds: 10^5 do not (it ends at step 20, long before its 90 s), 25 do (it runs to its 30)."""
    monkeypatch.setattr(probe, "PROBE_STEPS", probe_steps)
    monkeypatch.setattr(probe, "PROBE_MIN_STEPS", min_steps)
    monkeypatch.setattr(probe, "PACE_FROM", 10)
    monkeypatch.setattr(probe, "PROBE_SCORE", -1.0)  # a probe that tells trains bounded
    trainer, seen = probe.probed_trainer(sky, small(seconds=600.0, contraction_fit="probe"), "cpu")
    assert seen.steps == probed and seen.seconds < 60.0
    assert (seen.share is None) == (seen.fit == "cameras") == (min_steps > probed)


def test_a_budget_too_short_to_tell_trains_with_the_box_holding_the_cameras(sky, capsys):
    trainer, seen = probe.probed_trainer(sky, TrainConfig(steps=100, contraction_fit="probe", **SMALL), "cpu")
    assert seen.share is None and seen.steps == 0 and trainer.config.contraction_fit == "cameras"
    assert trainer.config.steps == 100 and trainer.step_count == 0
    _new_probed_trainer(sky, TrainConfig(steps=100, contraction_fit="probe", **SMALL), "cpu", show_progress=False)
    assert capsys.readouterr().err == ("contraction_fit=probe: the budget is too short for a probe: training "
                                       "contracted, the inner box holding the cameras\n")


def test_the_probe_is_left_out_where_nothing_is_contracted_or_the_files_contract(sky, monkeypatch):
    trainer, seen = probe.probed_trainer(sky, small(steps=5, contraction_fit="probe", aabb_scale=None), "cpu")
    assert seen is not None  # the scene's rule contracts it; a 5-step budget is too short to tell
    with pytest.raises(ValueError, match="decides whether to contract: leave contraction at auto"):
        TrainConfig(contraction=None, contraction_fit="probe").check()
    monkeypatch.setattr(sky, "contraction", "l2")  # the scene's files name their contraction: no probe
    trainer, seen = probe.probed_trainer(sky, small(steps=5, contraction_fit="probe"), "cpu")
    assert seen is None and trainer.config.contraction == "l2" and trainer.config.contraction_fit == "cameras"


def test_a_stop_in_steps_alone_counts_the_bar_in_steps_under_a_time_budget(sky, monkeypatch):
    from ngp_warp.training import trainer as trainer_module

    bars = []
    real = trainer_module.progress_bar
    monkeypatch.setattr(trainer_module, "progress_bar", lambda **kw: (bars.append(kw), real(**kw))[1])
    trainer = Trainer(sky, small(seconds=60.0), device="cpu")
    trainer.train(show_progress=False, stop=(3, None), desc="probe")  # the probe's bar: its steps
    spent = trainer.train_seconds
    trainer.train(show_progress=False, stop=(6, 30.0))  # a stop in seconds too: the bar counts seconds
    assert (bars[0]["total"], bars[0]["unit"]) == (3, "step") and bars[1]["unit"] == "s"
    assert bars[1]["total"] == pytest.approx(30.0 - spent)


def test_a_stopped_training_runs_the_schedule_of_the_whole_budget(sky, monkeypatch):
    """``Trainer.train(stop=...)`` (the probe's training) ends at the step given, each step's
    progress that of the whole budget's schedule; training on, for the steps left (a budget
    counts from where ``train`` starts), ends the schedule."""
    seen = []
    step = Trainer.step
    monkeypatch.setattr(Trainer, "step", lambda self, progress=0.0: (seen.append(progress), step(self, progress))[1])
    trainer = Trainer(sky, small(steps=20), device="cpu")
    trainer.train(show_progress=False, stop=(5, None), desc="probe")
    assert trainer.step_count == 5 and seen == pytest.approx([i / 20 for i in range(5)])
    trainer.config.steps = 15
    trainer.train(show_progress=False)
    assert trainer.step_count == 20 and seen == pytest.approx([i / 20 for i in range(20)])


def test_probe_needs_the_probed_trainer_and_is_refused_before_loading_where_it_cannot_run(sky, tmp_path, monkeypatch,
                                                                                          capsys):
    with pytest.raises(ValueError, match="decided by a short training"):
        Trainer(sky, TrainConfig(steps=1, contraction_fit="probe", **SMALL), device="cpu")
    not_a_scene = tmp_path / "empty"
    not_a_scene.mkdir()  # loading it would fail: the probe's refusal comes first
    from ngp_warp.training import distributed

    monkeypatch.setattr(distributed, "join_data_parallel", lambda args: True)  # a rank of --gpus 2
    assert main(["train", str(not_a_scene), "--out", str(tmp_path / "run"), "--steps", "8", "--device", "cpu",
                 "--set", "contraction_fit=probe"]) == 2
    assert "contraction_fit=probe: not supported with data-parallel training" in capsys.readouterr().err
    from ngp_warp.cli import train as train_cli

    given = []
    monkeypatch.setattr(train_cli, "train_and_report", lambda scene, out, args, config: given.append(config))
    assert main(["train", str(not_a_scene), "--out", str(tmp_path / "run"), "--steps", "8", "--device", "cpu"]) == 0
    assert given[0].contraction_fit == "cameras"  # data-parallel ranks do not probe
    with pytest.raises(UserError, match="not supported by view"):
        refuse_probe(TrainConfig(contraction_fit="probe"), "by view (it trains live)")
    refuse_probe(TrainConfig(contraction_fit="seen"), "by view")  # other fits pass


@pytest.mark.parametrize("error, code, says", [
    (KeyboardInterrupt, 130, "interrupted during the contraction probe, before the first checkpoint: nothing saved"),
    (TrainingDiverged("the loss is nan at step 7"), 2, "nan at step 7 (during the contraction probe; nothing was saved)"),
])
def test_a_probe_stopped_by_ctrl_c_or_a_diverged_loss_says_nothing_was_saved_and_leaves_no_folder(
        sky_folder, tmp_path, monkeypatch, capsys, error, code, says):
    train = Trainer.train

    def stopped_probe(self, *args, desc="train", **kwargs):
        if desc == "probe":
            raise error
        return train(self, *args, desc=desc, **kwargs)

    monkeypatch.setattr(Trainer, "train", stopped_probe)
    out = tmp_path / "run"
    assert main(["train", str(sky_folder), "--out", str(out), "--steps", "8000", "--no-video", "--device", "cpu",
                 "--quiet", "--set", "contraction_fit=probe"]) == code
    err = capsys.readouterr().err
    assert says in err and "Traceback" not in err
    assert not out.exists()


def test_train_says_what_the_probe_saw_and_counts_its_seconds_as_training(sky_folder, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(probe, "PROBE_STEPS", 6)
    monkeypatch.setattr(probe, "PROBE_MIN_STEPS", 4)
    monkeypatch.setattr(probe, "PROBE_BUDGET_SHARE", 0.75)
    monkeypatch.setattr(probe, "PROBE_SCORE", -1.0)  # an object: bounded
    out = tmp_path / "run"
    sets = ["contraction_fit=probe", "aabb_scale=2", "grid_resolution=16", "field.log2_hashmap_size=12",
            "field.n_levels=4", "field.hidden=16", "field.appearance_dim=0"]  # no codes to fit: a short evaluation
    assert main(["train", str(sky_folder), "--out", str(out), "--steps", "8", "--no-video", "--device", "cpu",
                 "--quiet", "--target-samples", "1024", *[a for kv in sets for a in ("--set", kv)]]) == 0
    err = capsys.readouterr().err
    assert "contraction_fit=probe: " in err and "after 6 steps" in err and "bounded in a box of 2," in err
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["steps"] == 8  # the new model's; the probe's 6 steps are not counted
    assert metrics["contraction_probe"]["fit"] == "bounded" and metrics["contraction_probe"]["steps"] == 6
    assert metrics["wall_seconds"]["training"] >= metrics["train_seconds"]  # the probe's seconds included


def test_auto_probes_where_the_scenes_own_rule_contracts_and_is_the_box_holding_the_cameras_elsewhere(
        sky, monkeypatch):
    monkeypatch.setattr(probe, "PROBE_STEPS", 4)
    monkeypatch.setattr(probe, "PROBE_MIN_STEPS", 4)
    monkeypatch.setattr(probe, "PROBE_BUDGET_SHARE", 0.5)
    assert TrainConfig().contraction_fit == "auto"
    trainer, seen = probe.probed_trainer(sky, small(steps=8), "cpu")
    assert seen is not None and seen.steps == 4 and trainer.config.contraction_fit == "cameras"
    for given in ({"contraction": "l2"}, {"contraction": None}):  # a contraction given: no probe
        trainer, seen = probe.probed_trainer(sky, small(steps=8, **given), "cpu")
        assert seen is None and trainer.config.contraction == given["contraction"]
    # a trainer made alone, or a run that cannot probe, takes the box holding the cameras
    alone = Trainer(sky, small(steps=1), device="cpu")
    assert alone.config.contraction == "l2" and alone.config.contraction_fit == "cameras"
    assert no_probe(small()).contraction_fit == "cameras" and no_probe(small(contraction_fit="seen")).contraction_fit == "seen"
    assert no_probe(None) is None
