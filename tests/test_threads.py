"""CPU launches split over threads give the same results as one thread (Warp's CPU atomics are
plain read-modify-writes, so kernels that add or max into shared memory must keep conflicting
items on one thread)."""

import pytest
import torch

from ngp_warp import HashGridEncoding, OccupancyGrid
from ngp_warp.ops.gather import embedding_rows


def _run(monkeypatch, threads: str, fn):
    monkeypatch.setenv("NGP_WARP_CPU_THREADS", threads)
    torch.manual_seed(3)
    return fn()


def test_occupancy_update_same_with_two_threads(monkeypatch):
    def update():
        grid = OccupancyGrid(torch.tensor([-1.0, -1, -1, 1, 1, 1]), resolution=32, levels=2)
        for step in range(0, 300, 16):  # warm-up and after: random and occupied cells, repeats
            grid.update(step, lambda x: torch.exp(-4 * x.norm(dim=-1)) * (x[:, 0] > -0.3))
        return grid.occs.clone(), grid.bitfield.clone()

    one, two = _run(monkeypatch, "1", update), _run(monkeypatch, "2", update)
    assert torch.equal(one[0], two[0]) and torch.equal(one[1], two[1])
    assert 0 < int((one[0] > 0.01).sum()) < one[0].numel()  # some cells on, some off


@pytest.mark.parametrize("levels,features", [(1, 2), (3, 1), (6, 2), (5, 4)])
def test_hash_grid_table_gradient_same_with_two_threads(monkeypatch, levels, features):
    # One level: both threads would add into the same small table at the same time.
    def grads():
        enc = HashGridEncoding(n_levels=levels, n_features_per_level=features, log2_hashmap_size=10,
                               base_resolution=4, per_level_scale=1.7)
        x = torch.rand(20000, 3, requires_grad=True)  # many points per cell: colliding updates
        (enc(x) * torch.randn(20000, enc.n_output_dims)).sum().backward()
        return enc.params.grad.clone(), x.grad.clone()

    one, two = _run(monkeypatch, "1", grads), _run(monkeypatch, "2", grads)
    torch.testing.assert_close(one[0], two[0], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(one[1], two[1], rtol=1e-5, atol=1e-6)
    assert one[0].abs().sum() > 0


def test_embedding_rows_gradient_same_with_two_threads(monkeypatch):
    # Enough chunks for two threads, each adding into the same two codes at every change of index.
    def grads():
        weight = torch.randn(2, 16, requires_grad=True)
        rows = torch.randint(0, 2, (200000,))
        (embedding_rows(weight, rows) * torch.randn(200000, 16)).sum().backward()
        return weight.grad.clone()

    one, two = _run(monkeypatch, "1", grads), _run(monkeypatch, "2", grads)
    assert torch.equal(one, two) and one.abs().sum() > 0
