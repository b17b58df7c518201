"""Data-parallel training with 2 gloo ranks on the CPU (ngp_warp.training.distributed): the same
parameters as one process on the combined batch, grid updates that agree, one stopping step."""

import dataclasses
import time

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from ngp_warp.ops.batch import sample_pixels
from ngp_warp.training.config import TrainConfig
from ngp_warp.data.loading import load_scene
from ngp_warp.training.distributed import make_data_parallel
from ngp_warp.ops.field import FieldConfig
from ngp_warp.ops.occupancy import OccupancyGrid
from ngp_warp.data.scene import write_demo_scene
from ngp_warp.training.trainer import Trainer

STEPS = 17  # crosses the grid refresh at step 16, the lr warm-up and the average's decay schedule
PIXELS = 128  # the combined batch; each of the 2 ranks trains on one half


CAPTURE = {"distortion_weight": 1e-2, "distortion_spacing": "normalised"}  # with appearance codes: fox's terms


def tiny_config(capture: bool = False, **budget) -> TrainConfig:
    return TrainConfig(**budget, target_samples=1 << 12, grid_resolution=16, steps_per_diagonal=128,
                       **(CAPTURE if capture else {}),
                       field=FieldConfig(n_levels=4, log2_hashmap_size=12, finest_resolution=32.0, hidden=16,
                                         appearance_dim=4 if capture else 0))


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    path = tmp_path_factory.mktemp("dp") / "scene"
    write_demo_scene(path, width=32, height=32, n_train=8, n_test=2, supersample=1)
    return path


def fixed_batches(trainer: Trainer, rows: slice):
    """sample_batch replaced: step k's batch is ``rows`` of a fixed PIXELS-pixel batch (and
    their images, for the appearance codes)."""
    def sample_batch(_n):
        b = sample_pixels(trainer.train_split, PIXELS, 1000 + trainer.step_count, 1)
        if trainer.field.appearance is not None:
            trainer.batch_images = b.pixels[rows, 0].long()
        return b.rays_o[rows], b.rays_d[rows], b.target[rows], b.background[rows]
    return sample_batch


def unjittered_render(trainer: Trainer):
    """The training render without stratified jitter (its offsets depend on the ray's index in
    the batch, which differs between a half and the combined batch)."""
    def render(rays_o, rays_d):
        phases, cfg = trainer.phases, trainer.config
        return trainer.model.render(rays_o, rays_d, phases.field, sigma_fn=phases.density,
                                    before_sync=phases.optimizer_update, return_samples=cfg.distortion_weight > 0,
                                    ray_images=trainer.batch_images)
    return render


def train_on_fixed_batches(scene_dir, rows: slice, parallel: bool, capture: bool = False) -> list[torch.Tensor]:
    trainer = Trainer(load_scene(scene_dir), tiny_config(capture, steps=STEPS), device="cpu")
    if parallel:
        make_data_parallel(trainer)
    trainer.phases = dataclasses.replace(trainer.phases, sample_batch=fixed_batches(trainer, rows),
                                         render=unjittered_render(trainer))
    for _ in range(STEPS):
        trainer.step(progress=trainer.step_count / STEPS)
    trainer.flush()
    return [p.detach().clone() for p in trainer.field.parameters()] + [trainer.grid.occs.clone()]


def _rank_main(rank: int, scene_dir, out_dir) -> None:
    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{out_dir}/store", rank=rank, world_size=2)
    half = PIXELS // 2
    rows = slice(rank * half, (rank + 1) * half)
    results = {"fixed": train_on_fixed_batches(scene_dir, rows, parallel=True),
               "capture": train_on_fixed_batches(scene_dir, rows, parallel=True, capture=True)}

    # grid updates: each cell's max over the ranks' densities
    grid = OccupancyGrid(torch.tensor([-1.0, -1, -1, 1, 1, 1]), resolution=16, levels=2)
    grid.merge_samples = lambda values: dist.all_reduce(values, op=dist.ReduceOp.MAX)
    torch.manual_seed(5)  # the update's jitter
    grid.update(0, lambda x: rank_density(x, rank))
    results["occs"] = grid.occs.clone()

    # a time budget: rank 1 is slower, both stop at rank 0's step; the models stay equal
    trainer = Trainer(load_scene(scene_dir), tiny_config(seconds=0.5), device="cpu")
    make_data_parallel(trainer)
    results["rays"] = trainer.sample_batch(256)[0]
    if rank == 1:
        slow = trainer.phases.backward
        trainer.phases = dataclasses.replace(trainer.phases, backward=lambda loss: (time.sleep(0.02), slow(loss)))
    trainer.train(show_progress=False)
    results["timed_steps"] = trainer.step_count
    results["timed_params"] = [p.detach().clone() for p in trainer.field.parameters()]
    torch.save(results, out_dir / f"rank{rank}.pt")
    dist.destroy_process_group()


def rank_density(x: torch.Tensor, rank: int) -> torch.Tensor:
    """A different positive density field on each rank."""
    return torch.exp(torch.sin(3.0 * x[:, 0] + rank * 2.0) * 2.0 + x[:, 1] * (1 - 2 * rank))


@pytest.mark.slow
def test_two_ranks_train_as_one_process_on_the_combined_batch(scene_dir, tmp_path):
    mp.spawn(_rank_main, args=(scene_dir, tmp_path), nprocs=2, join=True)
    ranks = [torch.load(tmp_path / f"rank{r}.pt") for r in range(2)]

    combined = train_on_fixed_batches(scene_dir, slice(0, PIXELS), parallel=False)
    first_half = train_on_fixed_batches(scene_dir, slice(0, PIXELS // 2), parallel=False)
    for rank in ranks:
        for got, want, alone in zip(rank["fixed"], combined, first_half, strict=True):
            torch.testing.assert_close(got, want, rtol=1e-4, atol=2e-5)  # Adam (eps 1e-15) magnifies rounding in tiny gradients
        assert any((a - b).abs().max() > 1e-3 for a, b in zip(rank["fixed"], first_half))
    # with a capture's terms: appearance codes (their gradients reduced too) and the distortion loss
    combined = train_on_fixed_batches(scene_dir, slice(0, PIXELS), parallel=False, capture=True)
    first_half = train_on_fixed_batches(scene_dir, slice(0, PIXELS // 2), parallel=False, capture=True)
    assert len(combined) == len(ranks[0]["fixed"]) + 1  # the codes
    for rank in ranks:
        for got, want in zip(rank["capture"], combined, strict=True):
            torch.testing.assert_close(got, want, rtol=1e-4, atol=2e-5)
        assert any((a - b).abs().max() > 1e-3 for a, b in zip(rank["capture"], first_half))

    # each cell: max(decay · old, max over the ranks' samples) = the update with the max density
    grid = OccupancyGrid(torch.tensor([-1.0, -1, -1, 1, 1, 1]), resolution=16, levels=2)
    torch.manual_seed(5)
    grid.update(0, lambda x: torch.maximum(rank_density(x, 0), rank_density(x, 1)))
    for rank in ranks:
        torch.testing.assert_close(rank["occs"], grid.occs, rtol=0, atol=0)
    assert not torch.equal(ranks[0]["rays"], ranks[1]["rays"])  # each rank its own rays

    # rank 0 decides at the readouts, every 10 steps
    assert ranks[0]["timed_steps"] == ranks[1]["timed_steps"] and ranks[0]["timed_steps"] % 10 == 0 \
        and ranks[0]["timed_steps"] >= 10
    for a, b in zip(ranks[0]["timed_params"], ranks[1]["timed_params"], strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
