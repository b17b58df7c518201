"""ray_loss: the fused photometric loss against its float64 twin, values and gradients."""

import pytest
import torch

from ngp_warp._reference import ray_loss as ray_loss_ref
from ngp_warp.ops.ray_loss import ray_loss

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)]


def rays(n: int, device: str, seed: int = 0, k: int = 1) -> dict:
    """n rays of n / k pixels."""
    g = torch.Generator().manual_seed(seed)
    return {
        "rgb": torch.rand(n, 3, generator=g) * 0.8,
        "opacity": torch.rand(n, generator=g),
        "target": torch.rand(n // k, 3, generator=g),
        "background": torch.rand(n // k, 3, generator=g),
        "ray_mask": torch.rand(n, generator=g) < 0.8,
        "extra": torch.rand(n, generator=g) * 0.1,
    }


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("pixels", [1, 37, 5000])
@pytest.mark.parametrize("k", [1, 4])
@pytest.mark.parametrize("huber_delta", [None, 0.1])
@pytest.mark.parametrize("optional", ["all", "no mask", "no extra"])
def test_values_and_gradients_match_the_float64_twin(device, pixels, k, huber_delta, optional):
    x = rays(pixels * k, "cpu", seed=pixels, k=k)
    if optional == "no mask":
        x["ray_mask"] = None
    if optional == "no extra":
        x["extra"] = None
    differentiable = [k for k in ("rgb", "opacity", "background", "extra") if x[k] is not None]
    ours = {k: (v.detach().to(device, copy=True).requires_grad_(k in differentiable) if v is not None else None) for k, v in x.items()}
    ref = {k: (v.detach().double().requires_grad_(k in differentiable) if v is not None and v.is_floating_point() else v)
           for k, v in x.items()}
    loss, mse = ray_loss(**ours, extra_weight=0.5, huber_delta=huber_delta, rays_per_pixel=k)
    ref_loss, ref_mse = ray_loss_ref.ray_loss(**ref, extra_weight=0.5, huber_delta=huber_delta, rays_per_pixel=k)
    assert loss.shape == () and mse.shape == () and not mse.requires_grad
    torch.testing.assert_close(loss.double().cpu(), ref_loss.detach(), rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(mse.double().cpu(), ref_mse.detach(), rtol=1e-5, atol=1e-7)
    (3.0 * loss).backward()
    (3.0 * ref_loss).backward()
    for k in differentiable:
        assert ref[k].grad.abs().max() > 0
        torch.testing.assert_close(ours[k].grad.double().cpu(), ref[k].grad, rtol=1e-4, atol=1e-8)


def test_a_background_without_gradient_gets_none():
    x = {k: v.requires_grad_(k == "rgb") for k, v in rays(40, "cpu", k=4).items()}
    ray_loss(**x, rays_per_pixel=4)[0].backward()
    assert x["background"].grad is None and x["rgb"].grad.abs().max() > 0


def test_the_loss_is_a_tensor_of_its_own():
    x = {k: v.requires_grad_(k == "rgb") for k, v in rays(50, "cpu").items()}
    loss, mse = ray_loss(**x)
    before = float(mse)
    loss += 1.0  # in place, as a user adding a regulariser might
    loss.backward()
    assert float(mse) == before and x["rgb"].grad.abs().max() > 0


def test_masked_rays_get_no_gradient():
    x = {k: v.requires_grad_(k in ("rgb", "opacity")) for k, v in rays(300, "cpu").items()}
    ray_loss(**x, extra_weight=1.0)[0].backward()
    dropped = ~x["ray_mask"]
    assert dropped.any() and x["rgb"].grad[dropped].abs().max() == 0 and x["opacity"].grad[dropped].abs().max() == 0


def test_a_pixel_with_a_dropped_ray_gets_no_gradient():
    x = {k: v.requires_grad_(k in ("rgb", "opacity", "extra")) for k, v in rays(400, "cpu", k=4).items()}
    ray_loss(**x, extra_weight=1.0, rays_per_pixel=4)[0].backward()
    dropped = (~x["ray_mask"]).view(100, 4).any(1).repeat_interleave(4)  # all four rays of such a pixel
    assert dropped.any() and (~dropped).any()
    for name in ("rgb", "opacity", "extra"):
        grad = x[name].grad
        assert grad[dropped].abs().max() == 0 and grad[~dropped].abs().min() > 0


def test_no_kept_ray_gives_zero_loss():
    x = rays(10, "cpu")
    x["ray_mask"] = torch.zeros(10, dtype=torch.bool)
    loss, mse = ray_loss(**x)
    assert float(loss) == 0.0 and float(mse) == 0.0


@pytest.mark.parametrize("bad", [
    dict(rgb=torch.zeros(5, 4)), dict(opacity=torch.zeros(4)), dict(target=torch.zeros(5, 3, dtype=torch.float64)),
    dict(background=torch.zeros(3)), dict(ray_mask=torch.ones(5)), dict(extra=torch.zeros(6)),
    dict(huber_delta=0.0), dict(extra_weight=-1.0), dict(huber_delta="0.1"), dict(extra_weight=None),
    dict(target=torch.zeros(5, 3, requires_grad=True)),
    dict(rays_per_pixel=0), dict(rays_per_pixel=2), dict(rays_per_pixel=5),  # 5 rays are one pixel of 5, not 5 pixels
])
def test_rejects_bad_inputs_with_a_clear_error(bad):
    x = {**rays(5, "cpu"), **bad}
    with pytest.raises(ValueError):
        ray_loss(**x)
