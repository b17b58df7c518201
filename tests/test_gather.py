"""Row gathers and scatters (the renderer's index work) against their row-by-row twins: every
dtype and row width the renderer moves, the fallbacks, input checks, and CPU against CUDA."""

import pytest
import torch

from ngp_warp._reference import gather as ref
from ngp_warp.ops.gather import gather_rows, scatter_rows

CASES = [  # (shape, dtype): h in bf16, positions, sigmas, int64 indices, int32 offsets, bool (fallback), odd bf16
    ((500, 16), torch.bfloat16), ((500, 3), torch.float32), ((500,), torch.float32), ((500,), torch.int64),
    ((500,), torch.int32), ((500,), torch.bool), ((500, 3), torch.bfloat16),
]


def random_rows_of(shape, dtype, g):
    if dtype == torch.bool:
        return torch.rand(shape, generator=g) < 0.5
    if dtype in (torch.int32, torch.int64):
        return torch.randint(-2**30, 2**30, shape, generator=g).to(dtype)
    return (torch.randn(shape, generator=g) * 100).to(dtype)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
@pytest.mark.parametrize("shape,dtype", CASES)
def test_gather_and_scatter_match_the_row_by_row_twins(device, shape, dtype):
    g = torch.Generator().manual_seed(len(shape) * 7 + shape[-1])
    src = random_rows_of(shape, dtype, g).to(device)
    rows = torch.randperm(shape[0], generator=g)[:300].sort().values.to(device)  # sorted, as the renderer's
    rows[::7] = rows[::7].flip(0)  # and some out of order
    got = gather_rows(src, rows)
    assert got.dtype == dtype and torch.equal(got.cpu(), ref.gather_rows(src.cpu(), rows.cpu()))
    values = random_rows_of((300, *shape[1:]), dtype, g).to(device)
    dst, want = src.clone(), src.cpu().clone()
    scatter_rows(dst, rows, values)
    ref.scatter_rows(want, rows.cpu(), values.cpu())
    assert torch.equal(dst.cpu(), want) and not torch.equal(dst.cpu(), src.cpu())


def test_empty_rows_and_sources_the_kernel_cannot_take():
    src = torch.randn(50, 4)
    assert gather_rows(src, torch.zeros(0, dtype=torch.int64)).shape == (0, 4)
    assert gather_rows(torch.zeros(0, 3), torch.zeros(0, dtype=torch.int64)).shape == (0, 3)
    rows = torch.tensor([3, 0, 48])
    strided = src[:, ::2]  # not contiguous: torch's indexing
    odd = torch.randn(101, dtype=torch.float32).to(torch.bfloat16)[1:].view(50, 2)  # 2-byte aligned only
    for t in (strided, odd):
        assert torch.equal(gather_rows(t, rows), t[rows])
        dst, want = t.clone() if t is strided else t, t.clone()
        values = torch.randn(3, *t.shape[1:]).to(t.dtype)
        scatter_rows(dst, rows, values)
        want[rows] = values
        assert torch.equal(dst, want)


@pytest.mark.parametrize("bad", [
    {"rows": torch.tensor([1, 2], dtype=torch.int32)}, {"rows": torch.ones(2, 2, dtype=torch.int64)},
    {"src": "h"}, {"values": torch.zeros(2, 4, dtype=torch.float64)}, {"values": torch.zeros(3, 4)},
    {"values": [[0.0] * 4] * 2},
])
def test_bad_inputs_are_one_line_errors(bad):
    args = {"src": torch.zeros(10, 4), "rows": torch.tensor([1, 2]), "values": torch.zeros(2, 4)}
    args.update(bad)
    with pytest.raises(ValueError):
        if "values" in bad:
            scatter_rows(args["src"], args["rows"], args["values"])
        else:
            gather_rows(args["src"], args["rows"])


@pytest.mark.cuda
def test_cuda_matches_cpu_on_the_renderers_rows():
    g = torch.Generator().manual_seed(3)
    h = torch.randn(100_000, 16, generator=g).to(torch.bfloat16)
    rows = torch.randint(0, 100_000, (40_000,), generator=g).sort().values
    assert torch.equal(gather_rows(h.cuda(), rows.cuda()).cpu(), gather_rows(h, rows))
