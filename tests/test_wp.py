"""The launch helper: every item handled exactly once, CPU splitting respects ``align``."""

import pytest
import torch
import warp as wp

from ngp_warp import _wp


@wp.kernel
def _mark(first: int, out: wp.array(dtype=wp.int32), owner: wp.array(dtype=wp.int32), scale: int,
          maybe: wp.array(dtype=wp.float32)):
    i = first + wp.tid()
    out[i] = out[i] + i * scale
    owner[i] = first  # which chunk handled item i
    if maybe:
        maybe[i] = float(i)


@pytest.mark.parametrize("threads,n,align", [("1", 5000, 1), ("2", 10001, 1), ("2", 9000, 4096), ("3", 7, 1)])
def test_cpu_launch_covers_each_item_once(monkeypatch, threads, n, align):
    monkeypatch.setenv("NGP_WARP_CPU_THREADS", threads)
    out = torch.zeros(n, dtype=torch.int32)
    owner = torch.full((n,), -1, dtype=torch.int32)
    _wp.launch(_mark, n, [out, owner, 3, None], "cpu", align=align)
    assert torch.equal(out, torch.arange(n, dtype=torch.int32) * 3)  # once each, never twice
    starts = owner.unique().tolist()
    assert all(s % align == 0 for s in starts)
    if threads != "1" and n >= 2 * 2048 and align < n:
        assert len(starts) > 1  # the range really was split


def test_launch_optional_array_and_zero_items():
    out = torch.zeros(10, dtype=torch.int32)
    owner = torch.zeros(10, dtype=torch.int32)
    maybe = torch.zeros(10)
    _wp.launch(_mark, 10, [out, owner, 1, maybe], "cpu")
    assert torch.equal(maybe, torch.arange(10, dtype=torch.float32))
    _wp.launch(_mark, 0, [out, owner, 1, maybe], "cpu")  # nothing to do, nothing done
    assert torch.equal(out, torch.arange(10, dtype=torch.int32))
    with pytest.raises(RuntimeError, match="inputs"):
        _wp.launch(_mark, 10, [out, owner, 1], "cpu")


def test_to_wp_rejects_a_wrong_dtype():
    with pytest.raises(RuntimeError):
        _wp.to_wp(torch.zeros(4, 2, dtype=torch.float32), dtype=wp.vec3)


@pytest.mark.cuda
def test_cuda_launch_matches_cpu():
    out = torch.zeros(5000, dtype=torch.int32, device="cuda")
    owner = torch.zeros(5000, dtype=torch.int32, device="cuda")
    _wp.launch(_mark, 5000, [out, owner, 2, None], _wp.device_of(out))
    assert torch.equal(out.cpu(), torch.arange(5000, dtype=torch.int32) * 2)
