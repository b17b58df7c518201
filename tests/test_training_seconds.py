"""The training loop's clock: what a time budget counts, and how its progress bar ends."""

import dataclasses
import time

from ngp_warp.data.loading import load_scene
from ngp_warp.training.trainer import Trainer
from test_train import tiny_config, tiny_scene  # noqa: F401  (tiny_scene: a fixture)


def test_training_seconds_count_the_loops_own_work_but_not_checkpoints(tiny_scene, monkeypatch):
    trainer = Trainer(load_scene(tiny_scene), tiny_config(20), device="cpu")
    show, step, stepped = trainer._show_readout, trainer.step, []

    def slow_readout(bar):  # the loop's work between steps: 0.05 s a call
        time.sleep(0.05)
        show(bar)

    def timed_step(progress_done):
        before = trainer.train_seconds
        stats = step(progress_done)
        stepped.append(trainer.train_seconds - before)
        return stats

    monkeypatch.setattr(trainer, "_show_readout", slow_readout)
    monkeypatch.setattr(trainer, "step", timed_step)
    began = time.perf_counter()
    trainer.train(show_progress=False, checkpoint=lambda: time.sleep(0.2), checkpoint_every=0.0)
    wall = time.perf_counter() - began
    # readouts at steps 1, 10 and 20, each reads twice in the loop (the last readout, then
    # before its checkpoint): at least 0.3 s counted outside the steps; the three checkpoints'
    # 0.6 s not counted, nor any step twice
    assert len(stepped) == 20 and trainer.train_seconds - sum(stepped) >= 0.3
    assert wall - trainer.train_seconds >= 0.6


def test_a_time_budget_s_bar_ends_at_its_total(tiny_scene, monkeypatch):
    import io
    import warnings

    import ngp_warp.training.trainer as trainer_module

    bars = []

    def recorded(*args, **kwargs):
        bars.append(progress(*args, **{**kwargs, "file": io.StringIO()}))
        return bars[-1]

    progress = trainer_module.progress_bar
    monkeypatch.setattr(trainer_module, "progress_bar", recorded)
    config = dataclasses.replace(tiny_config(1), steps=None, seconds=0.5)
    trainer = Trainer(load_scene(tiny_scene), config, device="cpu")
    step = trainer.step

    def slow_step(progress_done):  # each step takes 0.6 s more: the first ends 0.1 s past the budget
        stats = step(progress_done)
        trainer.train_seconds += 0.6
        return stats

    monkeypatch.setattr(trainer, "step", slow_step)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # tqdm warns of a count past its total
        trainer.train(show_progress=True)
    assert trainer.train_seconds >= 0.6 and bars[0].n == bars[0].total == 0.5
