"""What the environment tells a process about its rank (``WORLD_SIZE``, ``LOCAL_RANK``, as
torchrun and ``ngp-warp --gpus`` set them), without torch: the command line reads it before
torch loads."""

from __future__ import annotations

import os


def started_as_rank() -> bool:
    """Whether this process is one of several ranks (``WORLD_SIZE`` > 1: ``--gpus`` or torchrun)."""
    return int(os.environ.get("WORLD_SIZE", "1")) > 1


def reports() -> bool:
    """Whether this process reports the mistakes every rank makes: not one of several ranks, or
    the first rank of its machine (``LOCAL_RANK`` 0)."""
    return not started_as_rank() or os.environ.get("LOCAL_RANK", "0") == "0"
