"""LazyAdam: torch's Adam where every gradient is non-zero, its float64 twin where some are zero."""

import pytest
import torch

from ngp_warp._reference import optim as optim_ref
from ngp_warp.ops.optim import LazyAdam


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
def test_rejects_bad_settings(bad):
    with pytest.raises(ValueError):
        LazyAdam([torch.nn.Parameter(torch.zeros(4))], **bad)


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
