"""Which capture scenes ``grid_seen_only`` can change: the share of a refresh's sample points
that the rule zeroes.

    python benchmarks/unseen_share.py [--scenes demo-colmap,room-colmap,...] [--lego DIR] [--fox DIR]
                                      [--work DIR] [--rounds 4]

For each scene of ``bench_captures.py`` (written into ``--work`` once), builds the trainer the
command line builds with ``grid_seen_only=true`` (a probed scene both ways: contracted with the
box holding the cameras, and bounded), draws a jittered point in every cell ``--rounds`` times,
as the grid's warm-up refreshes do, and passes density 1 through the rule's kernel. A scene
where no point is zeroed trains exactly as without the rule.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
import bench_captures  # noqa: E402
from ngp_warp.data.loading import load_scene  # noqa: E402
from ngp_warp.ops.contraction import uncontract  # noqa: E402
from ngp_warp.training.config import TrainConfig  # noqa: E402
from ngp_warp.training.contraction_probe import _bounded, _probes  # noqa: E402
from ngp_warp.training.trainer import Trainer  # noqa: E402

CHUNK = 1 << 18


def zeroed_share(trainer: Trainer, rounds: int = 4) -> tuple[float, int, int]:
    """(share of the drawn points in visible cells that the rule zeroes, cells with such a point,
    visible cells) of ``trainer``'s grid after :meth:`OccupancyGrid.count_seen_only`."""
    grid = trainer.grid
    visible = grid.occs.reshape(-1) >= 0
    touched = torch.zeros_like(visible)
    zeroed = total = 0
    for seed in range(rounds):
        for lo in range(0, grid.n_cells, CHUNK):
            m = min(CHUNK, grid.n_cells - lo)
            cells, points = grid._draw(lo, m, True, grid.n_cells, 1234 + seed, None)
            if grid.contraction is not None:
                points = uncontract(points, grid.contraction, grid.inner_aabb, check_box=False)
            density = torch.ones(m, device=points.device)
            grid._zero_unseen(points, density)
            counted = visible[cells.long()]
            gone = counted & (density == 0)
            zeroed, total = zeroed + int(gone.sum()), total + int(counted.sum())
            touched[cells.long()[gone]] = True
    return zeroed / max(total, 1), int(touched.sum()), int(visible.sum())


def variants(scene) -> list[tuple[str, TrainConfig]]:
    """The trainings a scene may get by default: a probed scene's two, else one."""
    config = TrainConfig(grid_seen_only=True)
    cameras = dataclasses.replace(config, contraction_fit="cameras")
    if not _probes(config, scene):
        return [("default", cameras)]
    return [("probed: contracted", cameras), ("probed: bounded", _bounded(config))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default=",".join(n for n in bench_captures.SCENES if "nerf-synthetic" not in n))
    ap.add_argument("--lego", type=Path, default=None)
    ap.add_argument("--fox", type=Path, default=None)
    ap.add_argument("--work", type=Path, default=Path("unseen_share"))
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()
    args.downscale = 1
    args.work.mkdir(parents=True, exist_ok=True)
    print("| scene | trains as | contraction | near | margin (px) | points zeroed | cells touched / visible |")
    print("| --- | --- | --- | ---: | ---: | ---: | ---: |")
    for name in args.scenes.split(","):
        scene = load_scene(bench_captures.scene_folder(name, args.work, args))
        for label, config in variants(scene):
            trainer = Trainer(scene, config, args.device)
            if trainer.grid._seen_frame is None:
                print(f"| {name} | {label} | | | | the rule does not apply (fisheye) | |")
                continue
            share, touched, visible = zeroed_share(trainer, args.rounds)
            print(f"| {name} | {label} | {trainer.config.contraction or 'none'} | {trainer.model.march.near:.3f} | "
                  f"{trainer.grid._seen_frame[3]:.2f} | {100 * share:.3f} % | {touched:,} / {visible:,} |", flush=True)
            del trainer


if __name__ == "__main__":
    main()
