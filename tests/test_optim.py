"""Adam: torch's Adam, and its state dicts. LazyAdam: torch's Adam where every gradient is
non-zero, its float64 twin where some are zero."""

import subprocess
import sys

import pytest
import torch

from ngp_warp._reference import optim as optim_ref
from ngp_warp.ops.optim import Adam, LazyAdam


def sparse_grads(n: int, steps: int, seed: int = 0) -> list[torch.Tensor]:
    """Random gradients of mixed scale; about half the entries are zero in each step."""
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(n, generator=g) * 10 ** torch.empty(n).uniform_(-4, 0, generator=g)
            * (torch.rand(n, generator=g) < 0.5) for _ in range(steps)]


def run(opt_cls, param: torch.Tensor, grads, **kw) -> torch.Tensor:
    p = torch.nn.Parameter(param.clone())
    opt = opt_cls([p], **kw)
    for g in grads:
        p.grad = g.to(p.device).clone()
        opt.step()
    return p.detach()


def test_equals_torch_adam_when_every_gradient_is_non_zero():
    p0 = torch.randn(5000)
    grads = [torch.randn(5000) + 0.01 for _ in range(6)]
    assert all((g != 0).all() for g in grads)
    kw = dict(lr=1e-2, betas=(0.9, 0.99), eps=1e-15)
    ours, theirs = run(LazyAdam, p0, grads, **kw), run(torch.optim.Adam, p0, grads, **kw)
    assert (ours - p0).abs().min() > 0  # every entry moved
    torch.testing.assert_close(ours, theirs, rtol=0, atol=1e-6)


@pytest.mark.parametrize("weight_decay", [0.0, 0.5])
def test_skips_zero_gradient_entries_like_its_float64_twin(weight_decay):
    p0 = torch.randn(20000)
    grads = sparse_grads(20000, steps=8)
    ours = run(LazyAdam, p0, grads, lr=1e-2, weight_decay=weight_decay)
    ref = optim_ref.lazy_adam(p0, grads, lr=1e-2, weight_decay=weight_decay)
    torch.testing.assert_close(ours.double(), ref, rtol=0, atol=2e-6)
    never = torch.stack(grads).eq(0).all(0)
    assert never.any() and torch.equal(ours[never], p0[never])
    # torch's Adam moves entries after their gradient went back to zero: the two differ there
    dense = run(torch.optim.Adam, p0, grads, lr=1e-2, betas=(0.9, 0.99), eps=1e-15)
    assert ((dense - ours).abs() > 1e-4).float().mean() > 0.2


def test_state_dict_round_trip_resumes_the_same_trajectory():
    p0 = torch.randn(3000)
    grads = sparse_grads(3000, steps=6, seed=1)
    straight = run(LazyAdam, p0, grads, lr=5e-3)
    p = torch.nn.Parameter(p0.clone())
    opt = LazyAdam([p], lr=5e-3)
    for g in grads[:3]:
        p.grad = g.clone()
        opt.step()
    resumed = LazyAdam([p], lr=5e-3)
    resumed.load_state_dict(opt.state_dict())
    for g in grads[3:]:
        p.grad = g.clone()
        resumed.step()
    torch.testing.assert_close(p.detach(), straight, rtol=0, atol=0)


def test_weight_decay_shrinks_touched_entries_only():
    p0 = torch.randn(4000)
    grads = sparse_grads(4000, steps=3, seed=3)
    plain, decayed = run(LazyAdam, p0, grads, lr=1e-2), run(LazyAdam, p0, grads, lr=1e-2, weight_decay=2.0)
    touched = torch.stack(grads).ne(0).any(0)
    assert (decayed[touched].abs() < plain[touched].abs()).float().mean() > 0.9
    torch.testing.assert_close(decayed[~touched], p0[~touched], rtol=0, atol=0)


def run_averaged(param: torch.Tensor, grads, decays, flush_every: int = 0, **kw):
    """(param, average) after LazyAdam steps that keep an average with these decays."""
    p = torch.nn.Parameter(param.clone())
    average = param.clone()
    opt = LazyAdam([p], **kw)
    opt.keep_average(p, average)
    for i, (g, d) in enumerate(zip(grads, decays, strict=True), start=1):
        p.grad = g.to(p.device).clone()
        opt.param_groups[0]["average_decay"] = d
        opt.step()
        if flush_every and i % flush_every == 0:
            opt.flush_averages()
    opt.flush_averages()
    return p.detach(), average


@pytest.mark.parametrize("flush_every", [0, 3])
def test_kept_average_equals_a_dense_average_of_its_float64_twin(flush_every):
    p0 = torch.randn(20000)
    grads = sparse_grads(20000, steps=9, seed=4)
    decays = [0.1, 0.5, 0.9, 0.95, 0.3, 0.99, 0.995, 0.995, 0.7]
    ours, average = run_averaged(p0, grads, decays, flush_every, lr=1e-2)
    ref, ref_average = optim_ref.lazy_adam(p0, grads, lr=1e-2, average_decays=decays)
    torch.testing.assert_close(ours.double(), ref, rtol=0, atol=2e-6)
    torch.testing.assert_close(average.double(), ref_average, rtol=0, atol=2e-6)
    # the average differs from the weights, and from an average of touched steps only
    assert (average - ours).abs().max() > 1e-3
    plain = run(LazyAdam, p0, grads, lr=1e-2)
    torch.testing.assert_close(ours, plain, rtol=0, atol=0)  # keeping the average moves nothing else


def test_kept_average_stays_exact_across_log_decay_rebases():
    p0 = torch.randn(5000)
    grads = sparse_grads(5000, steps=60, seed=6)
    decays = [0.1] * 60  # log 0.1 = −2.3 per step: rebased at about step 28
    ours, average = run_averaged(p0, grads, decays, lr=1e-2)
    ref, ref_average = optim_ref.lazy_adam(p0, grads, lr=1e-2, average_decays=decays)
    torch.testing.assert_close(ours.double(), ref, rtol=0, atol=2e-6)
    torch.testing.assert_close(average.double(), ref_average, rtol=0, atol=2e-6)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
def test_a_second_flush_of_the_kept_average_changes_nothing(device):
    # the average far from the weights. On CUDA the fused multiply-add of the updates leaves
    # a − p inexact, so p + (a − p) can round away from a; the CPU build's a − p is exact
    p = torch.nn.Parameter(torch.randn(20000, device=device))
    average = 1e-3 * torch.randn(20000, device=device)
    opt = LazyAdam([p], lr=1e-2)
    opt.keep_average(p, average)
    for g in sparse_grads(20000, steps=4, seed=7):
        p.grad, opt.param_groups[0]["average_decay"] = g.to(device), 0.999
        opt.step()
    opt.flush_averages()  # a checkpoint saved
    once = average.clone()
    assert not torch.equal(once, p.detach())
    opt.flush_averages()  # and saved again: the same average, bit for bit
    torch.testing.assert_close(average, once, rtol=0, atol=0)


def test_kept_average_resumes_from_a_state_dict():
    p0 = torch.randn(3000)
    grads = sparse_grads(3000, steps=6, seed=5)
    decays = [0.5, 0.8, 0.9, 0.9, 0.95, 0.95]
    _, straight = run_averaged(p0, grads, decays, lr=5e-3)
    p, average = torch.nn.Parameter(p0.clone()), p0.clone()
    opt = LazyAdam([p], lr=5e-3)
    opt.keep_average(p, average)
    for g, d in zip(grads[:3], decays[:3]):
        p.grad, opt.param_groups[0]["average_decay"] = g.clone(), d
        opt.step()
    opt.flush_averages()  # as a checkpoint saves it
    saved_state, saved_average = opt.state_dict(), average.clone()
    resumed_average = saved_average.clone()
    resumed = LazyAdam([p], lr=5e-3)
    resumed.keep_average(p, resumed_average)
    resumed.load_state_dict(saved_state)
    for g, d in zip(grads[3:], decays[3:]):
        p.grad, resumed.param_groups[0]["average_decay"] = g.clone(), d
        resumed.step()
    resumed.flush_averages()
    torch.testing.assert_close(resumed_average, straight, rtol=1e-6, atol=1e-6)  # the flush rounds


def test_kept_average_needs_a_decay_and_a_matching_tensor():
    p = torch.nn.Parameter(torch.randn(10))
    opt = LazyAdam([p])
    with pytest.raises(ValueError, match="like the parameter"):
        opt.keep_average(p, torch.zeros(11))
    with pytest.raises(ValueError, match="not a parameter"):
        opt.keep_average(torch.nn.Parameter(torch.randn(10)), torch.zeros(10))
    opt.keep_average(p, p.detach().clone())
    p.grad = torch.ones(10)
    with pytest.raises(ValueError, match="average_decay"):
        opt.step()


@pytest.mark.parametrize("bad", [dict(lr=-1.0), dict(betas=(0.9, 1.0)), dict(eps=-1e-8), dict(weight_decay=-1.0)])
@pytest.mark.parametrize("opt_cls", [Adam, LazyAdam])
def test_rejects_bad_settings(bad, opt_cls):
    with pytest.raises(ValueError):
        opt_cls([torch.nn.Parameter(torch.zeros(4))], **bad)


def adam_groups(dtype: torch.dtype, seed: int = 0) -> list[dict]:
    """Two groups of random parameters, the second with L2 weight decay."""
    g = torch.Generator().manual_seed(seed)
    return [{"params": [torch.nn.Parameter(torch.randn(*s, generator=g).to(dtype)) for s in ((64, 32), (7,))]},
            {"params": [torch.nn.Parameter(torch.randn(16, 64, generator=g).to(dtype))], "weight_decay": 0.3}]


def adam_steps(opt, groups: list[dict], steps: range, seed: int = 1) -> None:
    """Random float32 gradients (the same for every caller and dtype); the first parameter has
    none at step 2, so the step skips it."""
    params = [p for group in groups for p in group["params"]]
    for i in steps:
        g = torch.Generator().manual_seed(seed + i)
        for k, p in enumerate(params):
            grad = torch.randn(p.shape, generator=g) * 10.0 ** (k - 2)
            p.grad = None if (i == 2 and k == 0) else grad.to(p.dtype)
        opt.step()


def test_adam_equals_torch_adam_in_float64():
    ours, theirs = adam_groups(torch.float32), adam_groups(torch.float64)
    kw = dict(lr=1e-2, betas=(0.9, 0.99), eps=1e-15)
    adam_steps(Adam(ours, **kw), ours, range(6))
    adam_steps(torch.optim.Adam(theirs, foreach=False, **kw), theirs, range(6))
    start = adam_groups(torch.float64)
    for a, b, p0 in zip(*([p for gr in x for p in gr["params"]] for x in (ours, theirs, start))):
        assert (b - p0).abs().min() > 0  # every entry moved
        torch.testing.assert_close(a.detach().double(), b.detach(), rtol=0, atol=2e-6)


@pytest.mark.parametrize("saved_by", [Adam, torch.optim.Adam])
def test_adam_resumes_from_a_state_dict_of_its_own_or_of_torchs(saved_by):
    """A state saved after 3 steps resumes the trajectory of 6 straight steps: exactly from its own
    state, to rounding from torch's (checkpoints written with torch.optim.Adam load)."""
    kw = dict(lr=5e-3, betas=(0.9, 0.99), eps=1e-15)
    straight = adam_groups(torch.float32)
    adam_steps(Adam(straight, **kw), straight, range(6))
    groups = adam_groups(torch.float32)
    first = saved_by(groups, **kw)
    adam_steps(first, groups, range(3))
    resumed = Adam(groups, **kw)
    resumed.load_state_dict(first.state_dict())
    adam_steps(resumed, groups, range(3, 6))
    tol = 0 if saved_by is Adam else 1e-6
    for a, b in zip(*([p for gr in x for p in gr["params"]] for x in (groups, straight))):
        torch.testing.assert_close(a.detach(), b.detach(), rtol=0, atol=tol)
    with pytest.raises(ValueError, match="parameter groups"):
        Adam(groups[:1], **kw).load_state_dict(first.state_dict())


def test_training_neither_imports_torch_dynamo():
    """Building and stepping the trainer's optimizers leaves torch._dynamo unimported (its import
    is 1-2 s of start-up); torch.optim's Adam would import it."""
    code = """
import sys, torch
from ngp_warp.ops.optim import Adam, LazyAdam
p, q = torch.nn.Parameter(torch.randn(8)), torch.nn.Parameter(torch.randn(8))
for opt, t in ((Adam([p], weight_decay=0.1), p), (LazyAdam([q]), q)):
    t.grad = torch.randn(8)
    opt.step()
    opt.load_state_dict(opt.state_dict())
assert "torch._dynamo" not in sys.modules, "imported torch._dynamo"
torch.optim.Adam([p])
assert "torch._dynamo" in sys.modules  # the check can tell
"""
    subprocess.run([sys.executable, "-c", code], check=True, timeout=300)


def test_rejects_non_float32_parameters():
    with pytest.raises(ValueError, match="float32"):
        LazyAdam([torch.nn.Parameter(torch.zeros(4, dtype=torch.float64))])


@pytest.mark.cuda
def test_cuda_matches_cpu():
    p0 = torch.randn(50000)
    grads = sparse_grads(50000, steps=5, seed=2)
    cpu = run(LazyAdam, p0, grads, lr=1e-2)
    gpu = run(LazyAdam, p0.cuda(), grads, lr=1e-2).cpu()
    torch.testing.assert_close(gpu, cpu, rtol=0, atol=1e-6)
    decays = [0.5, 0.9, 0.99, 0.95, 0.995]
    cpu_average = run_averaged(p0, grads, decays, lr=1e-2)[1]
    gpu_average = run_averaged(p0.cuda(), grads, decays, lr=1e-2)[1].cpu()
    torch.testing.assert_close(gpu_average, cpu_average, rtol=0, atol=1e-6)
    cpu_groups, gpu_groups = adam_groups(torch.float32), adam_groups(torch.float32)
    for group in gpu_groups:
        group["params"] = [torch.nn.Parameter(p.detach().cuda()) for p in group["params"]]
    adam_steps(Adam(cpu_groups, lr=1e-2), cpu_groups, range(4))
    adam_steps(Adam(gpu_groups, lr=1e-2), gpu_groups, range(4))
    for a, b in zip(*([p for gr in x for p in gr["params"]] for x in (gpu_groups, cpu_groups))):
        torch.testing.assert_close(a.detach().cpu(), b.detach(), rtol=0, atol=1e-6)
