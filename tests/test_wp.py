"""The launch helper: every item handled exactly once, CPU splitting respects ``align``; the Warp
internals it relies on (``ngp_warp/_warp_private.py``) are as tested, and the public ``wp.launch``
path that replaces them otherwise gives the same results."""

import warnings

import pytest
import torch
import warp as wp

from ngp_warp import HashGridEncoding, _warp_private, _wp


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


# -- the Warp internals behind ngp_warp/_warp_private.py ---------------------------------------


def test_warp_internals_are_as_tested():
    """Fails, naming what changed, when a Warp release changes an internal the launch replay uses."""
    found = _warp_private.problems()
    assert not found, f"warp-lang {wp.__version__} (tested: {_warp_private.TESTED_WARP}) changed: {found}"
    out, owner = torch.zeros(8, dtype=torch.int32), torch.zeros(8, dtype=torch.int32)
    _wp.launch(_mark, 8, [out, owner, 1, None], "cpu")
    cmd = _wp._command(_wp._signature(_mark), "cpu", 1)
    assert cmd is not None, f"a recorded wp.Launch changed: {_warp_private.problems()}"
    assert _warp_private.launch_problems(cmd) == [] and _warp_private.usable()


def test_replayed_launch_packs_arguments_as_wp_launch():
    """The arguments written into a recorded launch in place equal those wp.launch packs itself."""
    values = torch.rand(6, 2) + 0.5
    expected = values * 3.0
    _wp.launch(_warp_private._probe, 6, [values, 3.0], "cpu")  # values[i] *= scale
    assert torch.equal(values, expected)
    ours = _wp._command(_wp._signature(_warp_private._probe), "cpu", 1).params
    theirs = wp.launch(_warp_private._probe, dim=6, inputs=[0, wp.from_torch(values, dtype=wp.vec2), 3.0],
                       device="cpu", record_cmd=True).params
    assert len(ours) == len(theirs)
    assert ours[0].size == theirs[0].size == 6  # the launch bounds
    for mine, warps in zip(ours[1:], theirs[1:]):
        assert type(mine) is type(warps), f"Warp packs {type(warps)} where the replay writes {type(mine)}"
        if isinstance(mine, _warp_private.Descriptor):
            assert (mine.data, mine.shape[0], mine.strides[0], mine.ndim) == (
                warps.data, warps.shape[0], warps.strides[0], warps.ndim)
        else:
            assert mine.value == warps.value


def _launch_both_ways(monkeypatch):
    """(out, owner) of the _mark kernel, a vector array doubled (passed as a [4, 2] tensor) and a
    hash-grid encoding with its gradients."""
    monkeypatch.setenv("NGP_WARP_CPU_THREADS", "2")
    out = torch.zeros(10000, dtype=torch.int32)
    owner = torch.full((10000,), -1, dtype=torch.int32)
    _wp.launch(_mark, 10000, [out, owner, 3, None], "cpu", align=16)
    values = torch.arange(8.0).reshape(4, 2) + 1.0
    _wp.launch(_warp_private._probe, 4, [values, 2.0], "cpu")
    assert torch.equal(values, (torch.arange(8.0).reshape(4, 2) + 1.0) * 2.0)
    torch.manual_seed(5)
    enc = HashGridEncoding(3, 4, 2, 10, 4, 2.0)
    x = torch.rand(3000, 3, requires_grad=True)
    y = enc(x)
    (y * torch.randn_like(y)).sum().backward()
    return out, owner, y.detach(), enc.params.grad, x.grad


def test_public_launch_path_gives_the_same_results(monkeypatch):
    """The wp.launch path taken when Warp's internals changed: same results, one chunk."""
    out, owner, y, grad_params, grad_x = _launch_both_ways(monkeypatch)
    assert len(owner.unique()) > 1  # the replay split the range over threads
    monkeypatch.setattr(_warp_private, "_found", ["a simulated change"])
    monkeypatch.setattr(_warp_private, "_warned", True)
    out2, owner2, y2, grad_params2, grad_x2 = _launch_both_ways(monkeypatch)
    assert torch.equal(out2, out) and torch.equal(owner2, torch.zeros_like(owner2))  # one wp.launch
    assert torch.equal(y2, y) and torch.equal(grad_x2, grad_x)
    torch.testing.assert_close(grad_params2, grad_params, rtol=1e-5, atol=1e-6)  # other addition order


def test_a_changed_recorded_launch_warns_once_and_falls_back(monkeypatch):
    monkeypatch.setattr(_warp_private, "_found", [])
    monkeypatch.setattr(_warp_private, "_warned", False)
    monkeypatch.setattr(_warp_private, "launch_problems", lambda cmd: ["params_addr moved"])
    monkeypatch.setattr(_wp._local, "commands", {})
    out, owner = torch.zeros(10, dtype=torch.int32), torch.zeros(10, dtype=torch.int32)
    with pytest.warns(RuntimeWarning, match="params_addr moved"):
        _wp.launch(_mark, 10, [out, owner, 2, None], "cpu")
    assert torch.equal(out, torch.arange(10, dtype=torch.int32) * 2)
    assert not _warp_private.usable() and _warp_private.problems() == ["params_addr moved"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once only
        _wp.launch(_mark, 10, [out, owner, 2, None], "cpu")
    assert torch.equal(out, torch.arange(10, dtype=torch.int32) * 4)
