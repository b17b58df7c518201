"""Row gathers and scatters (the renderer's index work) against their row-by-row twins: every
dtype and row width the renderer moves, the fallbacks, input checks, and CPU against CUDA; the
appearance codes' embedding lookup, values and gradient, against its float64 twin."""

import pytest
import torch

from ngp_warp._reference import gather as ref
from ngp_warp.ops.gather import RUN, _words, embedding_rows, gather_rows, gather_words, scatter_rows, scatter_words

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
    values = random_rows_of((300, *shape[1:]), dtype, g).to(device)
    want = src.cpu().clone()
    ref.scatter_rows(want, rows.cpu(), values.cpu())
    words = _words(src)
    kernel = [] if words is None else [(lambda s, r: gather_words(s, r, words),
                                        lambda d, r, v: scatter_words(d, r, v, words))]
    for gather, scatter in [(gather_rows, scatter_rows), *kernel]:  # the kernels on this device too
        got = gather(src, rows)
        assert got.dtype == dtype and torch.equal(got.cpu(), ref.gather_rows(src.cpu(), rows.cpu()))
        dst = src.clone()
        scatter(dst, rows, values)
        assert torch.equal(dst.cpu(), want) and not torch.equal(dst.cpu(), src.cpu())
    assert bool(kernel) == (dtype != torch.bool and (shape, dtype) != ((500, 3), torch.bfloat16))  # whole words


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


def rows_in_runs(n_rows: int, n_weights: int, g: torch.Generator) -> torch.Tensor:
    """[n_rows] int64 in runs of 1–150 equal indices (a ray's samples), some runs longer than a
    thread's chunk, a few lone indices, neighbouring runs often of the same index."""
    runs = []
    while sum(len(r) for r in runs) < n_rows:
        length = int(torch.randint(1, 150, (1,), generator=g))
        runs.append(torch.full((length,), int(torch.randint(0, n_weights, (1,), generator=g))))
    return torch.cat(runs)[:n_rows]


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
@pytest.mark.parametrize("order", ["runs", "shuffled"])
def test_embedding_rows_matches_its_float64_twin_in_value_and_gradient(device, order):
    g = torch.Generator().manual_seed(11 if order == "runs" else 12)
    weight = torch.randn(57, 16, generator=g)
    rows = rows_in_runs(5000, 57, g)
    if order == "shuffled":
        rows = rows[torch.randperm(rows.shape[0], generator=g)]
    assert rows.shape[0] > 10 * RUN and rows.unique().numel() > 30
    upstream = torch.randn(rows.shape[0], 16, generator=g)
    w = weight.clone().to(device).requires_grad_(True)
    out = embedding_rows(w, rows.to(device))
    (out * upstream.to(device)).sum().backward()
    w64 = weight.double().requires_grad_(True)
    want = ref.embedding_rows(w64, rows)
    (want * upstream.double()).sum().backward()
    assert out.dtype == torch.float32 and torch.equal(out.detach().cpu(), want.detach().float())
    assert torch.allclose(w.grad.cpu().double(), w64.grad, rtol=1e-5, atol=1e-4)
    assert w.grad.abs().sum(1).gt(0).sum() == rows.unique().numel()  # the gradient reaches every row used


def test_embedding_rows_of_no_rows_and_bad_inputs():
    weight = torch.randn(5, 3, requires_grad=True)
    out = embedding_rows(weight, torch.zeros(0, dtype=torch.int64))
    out.sum().backward()
    assert out.shape == (0, 3) and torch.equal(weight.grad, torch.zeros(5, 3))
    for bad_weight in (torch.zeros(5, 3, dtype=torch.float64), torch.zeros(5), torch.zeros(3, 5).t()):
        with pytest.raises(ValueError):
            embedding_rows(bad_weight, torch.tensor([1, 2]))
    for bad_rows in (torch.tensor([1, 2], dtype=torch.int32), torch.tensor([0, 5]), torch.tensor([-1, 2])):
        with pytest.raises(ValueError):
            embedding_rows(weight, bad_rows)


def test_embedding_rows_refuses_a_second_derivative():
    weight = torch.randn(5, 3, requires_grad=True)
    out = embedding_rows(weight, torch.tensor([0, 0, 4, 2]))
    (grad,) = torch.autograd.grad((out ** 2).sum(), weight, create_graph=True)
    with pytest.raises(RuntimeError, match="differentiable once"):
        grad.sum().backward()
