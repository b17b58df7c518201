"""Row gathers and scatters: ``src[rows]`` and ``dst[rows] = values`` for the inference renderer
in one Warp launch of one thread per 4-byte word (see :mod:`ngp_warp.kernels.gather`), and
:func:`embedding_rows`, the differentiable lookup of per-image appearance codes per sample.

torch's own advanced indexing moves narrow rows (a sample's 16 bf16 features, its 12-byte
position) with one thread per row or per element, well below the memory's bandwidth on a GPU
(RESULTS.md); its embedding backward sorts every index. On the CPU, where a Warp launch runs on
one thread, torch's indexing is the faster one and :func:`gather_rows` and :func:`scatter_rows`
use it (the kernels stay reachable there through :func:`gather_words` and :func:`scatter_words`).
No gradient flows through :func:`gather_rows` and :func:`scatter_rows`.
"""

from __future__ import annotations

import math

import torch

from ngp_warp import _wp
from ngp_warp.ops._differentiable_once import refuse_second_derivative
from ngp_warp.kernels import gather as K

_MAX_WORDS = 2**31 - 1  # Warp indexes with int32


def _words(t: torch.Tensor) -> int | None:
    """4-byte words per row of ``t`` ([N, ...]), or None when it is not contiguous, not 4-byte
    aligned, empty, its rows are not whole words, or it has too many words for int32 indexing."""
    row_bytes = t.element_size() * math.prod(t.shape[1:])
    if (not t.is_contiguous() or t.numel() == 0 or row_bytes % 4 or t.data_ptr() % 4
            or t.numel() * t.element_size() // 4 > _MAX_WORDS):
        return None
    return row_bytes // 4


def _check(name: str, t: torch.Tensor, rows: torch.Tensor) -> None:
    if not isinstance(t, torch.Tensor) or t.dim() < 1:
        raise ValueError(f"{name} must be a tensor of rows, got {getattr(t, 'shape', type(t).__name__)}")
    if not isinstance(rows, torch.Tensor) or rows.dim() != 1 or rows.dtype != torch.int64 or rows.device != t.device:
        raise ValueError(f"rows must be a 1-D int64 tensor on {t.device}, got "
                         f"{getattr(rows, 'dtype', type(rows).__name__)} {tuple(getattr(rows, 'shape', ()))}")


def gather_rows(src: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """``src[rows]``: src [N, ...] any dtype, rows [K] int64 in [0, N) (not checked) → [K, ...].
    On CUDA one Warp launch (:func:`gather_words`); on the CPU, and for rows that are not whole
    4-byte words, torch's indexing."""
    _check("src", src, rows)
    words = _words(src)
    if src.device.type != "cuda" or words is None or rows.shape[0] * words > _MAX_WORDS:
        return src[rows]
    return gather_words(src, rows, words)


def gather_words(src: torch.Tensor, rows: torch.Tensor, words: int) -> torch.Tensor:
    """The kernel's ``src[rows]`` on any device: src [N, ...] with ``words`` = :func:`_words` of it
    (not None), rows [K] int64 in [0, N) → [K, ...] of src's dtype."""
    out = torch.empty((rows.shape[0], *src.shape[1:]), dtype=src.dtype, device=src.device)
    _wp.launch(K.gather_words, rows.shape[0] * words,
               [src.reshape(-1).view(torch.int32), rows, words, out.reshape(-1).view(torch.int32)], _wp.device_of(src))
    return out


def scatter_rows(dst: torch.Tensor, rows: torch.Tensor, values: torch.Tensor) -> None:
    """``dst[rows] = values`` in place: dst [N, ...], rows [K] int64, distinct, in [0, N) (not
    checked), values [K, ...] of dst's dtype and row shape. On CUDA one Warp launch
    (:func:`scatter_words`); on the CPU, and for rows that are not whole 4-byte words, torch's
    indexing."""
    _check("dst", dst, rows)
    if (not isinstance(values, torch.Tensor) or values.dtype != dst.dtype or values.device != dst.device
            or tuple(values.shape) != (rows.shape[0], *dst.shape[1:])):
        raise ValueError(f"values must be {dst.dtype} {[rows.shape[0], *dst.shape[1:]]} on {dst.device}, got "
                         f"{getattr(values, 'dtype', type(values).__name__)} {list(getattr(values, 'shape', []))}")
    words = _words(dst)
    if dst.device.type != "cuda" or words is None or _words(values) != words or rows.shape[0] * words > _MAX_WORDS:
        dst[rows] = values
        return
    scatter_words(dst, rows, values, words)


def scatter_words(dst: torch.Tensor, rows: torch.Tensor, values: torch.Tensor, words: int) -> None:
    """The kernel's ``dst[rows] = values`` on any device: dst [N, ...] and values [K, ...] of one
    dtype and row shape, contiguous, ``words`` = :func:`_words` of both; rows [K] int64, distinct."""
    _wp.launch(K.scatter_words, rows.shape[0] * words,
               [values.reshape(-1).view(torch.int32), rows, words, dst.reshape(-1).view(torch.int32)], _wp.device_of(dst))


RUN = 64  # rows summed per thread in the embedding's backward before its atomic adds


class _EmbeddingRows(torch.autograd.Function):
    """weight [N, A] float32, rows [K] int64 → weight[rows] [K, A]; the backward adds the incoming
    [K, A] gradient into [N, A] (:func:`ngp_warp.kernels.gather.add_rows_in_runs`), once
    differentiable."""

    @staticmethod
    def forward(ctx, weight: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(rows)
        ctx.n_weights = weight.shape[0]
        return gather_rows(weight, rows)

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        (rows,) = ctx.saved_tensors
        cols = grad_out.shape[1]
        grad_weight = torch.zeros(ctx.n_weights * cols, dtype=torch.float32, device=grad_out.device)
        items = -(-rows.shape[0] // RUN) * cols
        # one CPU thread: Warp's CPU atomics are plain read-modify-writes
        _wp.launch(K.add_rows_in_runs, items, [grad_out.float().contiguous().view(-1), rows, cols, RUN, grad_weight],
                   _wp.device_of(grad_out), align=items)
        return refuse_second_derivative("embedding_rows", (grad_weight.view(ctx.n_weights, cols),), (grad_out,))[0], None


def embedding_rows(weight: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """``weight[rows]`` with its gradient in ``weight``: an embedding lookup (the per-image
    appearance codes of packed samples) whose backward adds each run of equal indices once per
    column and chunk of rows, instead of sorting every index as torch's embedding does.
    Differentiable once (a second derivative through it raises).

    Args:
        weight: [N, A] float32, contiguous (A ≥ 1).
        rows: [K] int64 in [0, N), on weight's device; fastest when equal indices come in runs,
            as the samples of a ray do. Checked on the CPU; on CUDA not (a check would sync the
            device), where an index out of range reads and writes out of bounds.

    Returns:
        [K, A] float32.

    Raises:
        ValueError: one line, for inputs of the wrong dtype, shape or device, or (CPU) an index
            out of range.
    """
    _check("weight", weight, rows)
    if weight.dtype != torch.float32 or weight.dim() != 2 or weight.shape[1] < 1 or not weight.is_contiguous():
        raise ValueError(f"weight must be a contiguous [N, A] float32 tensor, got {weight.dtype} {tuple(weight.shape)}")
    if rows.device.type == "cpu" and rows.numel() and not 0 <= int(rows.min()) <= int(rows.max()) < weight.shape[0]:
        raise ValueError(f"rows must lie in [0, {weight.shape[0]}), got {int(rows.min())} to {int(rows.max())}")
    return _EmbeddingRows.apply(weight, rows)
