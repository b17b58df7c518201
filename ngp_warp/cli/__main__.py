"""``python -m ngp_warp.cli`` (as ``--gpus`` and torchrun run the ranks)."""

from ngp_warp.cli import run

run()
