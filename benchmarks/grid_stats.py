"""Where a trainer's samples go: samples per ray (median and mean) and the occupancy grid per cascade.

    from grid_stats import sample_stats   # benchmarks/ on sys.path, as bench_train.py has it

Used by ``bench_train.py --grid-stats``. The rays are a training batch (stratified march, as a
training step marches them); "marched" counts every sample the march emits, "trained" the ones in
front of early termination (transmittance ≥ the model's ``early_stop_eps`` under the field's
current densities), i.e. what a training step sends through the field with gradients.
"""

from __future__ import annotations

import torch

from ngp_warp.ops.prune import prune_samples
from ngp_warp.ops.raymarch import ray_marching


def _cascade_of(points: torch.Tensor, aabb: list[float], levels: int) -> torch.Tensor:
    """[S] int64 cascade of world points [S, 3] float32: the finest l whose box (the base box scaled
    by 2^l about its centre) holds them, clamped to levels - 1."""
    lo, hi = torch.tensor(aabb[:3], device=points.device), torch.tensor(aabb[3:], device=points.device)
    reach = ((points - (lo + hi) / 2).abs() / ((hi - lo) / 2)).amax(-1).clamp_min(1e-12)
    return torch.ceil(torch.log2(reach)).clamp(0, levels - 1).long()


def _quantiles(counts: torch.Tensor) -> dict:
    c = counts.float()
    return {"mean": float(c.mean()), "median": float(c.median()), "p90": float(torch.quantile(c, 0.9))}


@torch.no_grad()
def sample_stats(trainer, n_rays: int = 1 << 16) -> dict:
    """Samples per ray and the grid's occupancy of ``trainer`` (a :class:`ngp_warp.training.trainer.Trainer`).

    Returns:
        dict: ``marched`` / ``trained`` ({mean, median, p90} samples per ray over ``n_rays``
        training rays), ``trained_by_cascade`` (fraction of trained samples per cascade),
        ``occupied_by_cascade`` (fraction of each cascade's visible cells that are occupied)
        and ``threshold`` (the grid's last occupancy threshold).
    """
    trainer.flush()
    model, grid = trainer.model, trainer.grid
    rays_o, rays_d, _, _ = trainer.sample_batch(n_rays)
    with model.precision():
        samples = ray_marching(rays_o, rays_d, grid, model.march_options(stratified=True), validate=False)
        sigmas = model.field.density(samples.positions).float().reshape(-1).contiguous()
    pruned = prune_samples(samples, sigmas, model.early_stop_eps).samples
    marched = samples.ray_offsets.diff()
    trained = pruned.ray_offsets.diff()
    levels = grid.levels
    where = _cascade_of(pruned.positions, grid.aabb_host, levels) if grid.contraction is None else \
        torch.zeros(pruned.n_samples, dtype=torch.long, device=rays_o.device)
    by_cascade = torch.bincount(where, minlength=levels).float() / max(pruned.n_samples, 1)
    occs = grid.occs.reshape(levels, -1)
    occupied = grid.occupied().reshape(levels, -1)
    visible = (occs >= 0).sum(-1).clamp_min(1)
    return {
        "marched": _quantiles(marched), "trained": _quantiles(trained),
        "trained_by_cascade": [round(float(v), 4) for v in by_cascade],
        "occupied_by_cascade": [round(float(v), 4) for v in occupied.sum(-1) / visible],
        "threshold": float(grid.threshold),
    }


def format_stats(stats: dict) -> str:
    """One line for a benchmark's log."""
    m, t = stats["marched"], stats["trained"]
    return (f"per ray marched median {m['median']:.0f} mean {m['mean']:.1f} p90 {m['p90']:.0f} | trained median "
            f"{t['median']:.0f} mean {t['mean']:.1f} p90 {t['p90']:.0f} | trained by cascade "
            f"{stats['trained_by_cascade']} | occupied {stats['occupied_by_cascade']} | thr {stats['threshold']:.4g}")
