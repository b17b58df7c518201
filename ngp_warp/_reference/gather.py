"""Pure-torch twins of :mod:`ngp_warp.ops.gather`, one row at a time (tests only)."""

from __future__ import annotations

import torch


def gather_rows(src: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """``src[rows]``, row by row."""
    return torch.stack([src[int(r)] for r in rows]) if len(rows) else src[:0].clone()


def scatter_rows(dst: torch.Tensor, rows: torch.Tensor, values: torch.Tensor) -> None:
    """``dst[rows] = values``, row by row."""
    for i, r in enumerate(rows.tolist()):
        dst[r] = values[i]


def embedding_rows(weight: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """``weight[rows]``: weight [N, A] float64, rows [K] int64 → [K, A] float64, row by row,
    differentiable in ``weight`` through autograd."""
    return torch.stack([weight[int(r)] for r in rows]) if len(rows) else weight[:0] * 1
