"""A held-out view's appearance code, fitted on the left half of its image with the field frozen,
and the evaluation that scores it on the right half (CPU)."""

import json
from pathlib import Path

import imageio.v3 as iio
import pytest
import torch

from ngp_warp.training.appearance_fit import FIT_ITERATIONS, FIT_PULL, fit_appearance_code, nearest_training_code, right_half
from ngp_warp.training.config import TrainConfig
from ngp_warp.data.loading import load_scene
from ngp_warp.outputs.evaluate import depth_to_uint8, evaluate, iter_test_renders, to_uint8
from ngp_warp.ops.field import FieldConfig
from ngp_warp.outputs.metrics import psnr, ssim
from ngp_warp.data.scene import write_demo_scene
from ngp_warp.data.scene_unbounded import write_unbounded_scene
from ngp_warp.training.trainer import Trainer

FIT = {"iterations": 60}  # every left-half pixel of the 24-pixel views in each iteration


def small_config(steps: int) -> TrainConfig:
    return TrainConfig(steps=steps, target_samples=1 << 13, grid_resolution=32, steps_per_diagonal=256,
                       field=FieldConfig(n_levels=8, log2_hashmap_size=14, hidden=32))


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A trainer on the 24-pixel unbounded scene (appearance codes, weight average) after 60 steps,
    its last update applied and no gradients left in the field."""
    path = tmp_path_factory.mktemp("unbounded") / "scene"
    write_unbounded_scene(path, width=24, height=24, n_train=12, n_test=2, supersample=1)
    trainer = Trainer(load_scene(path), small_config(60), device="cpu")
    trainer.train(show_progress=False)
    trainer.flush()
    trainer.weights.zero_grad()
    assert trainer.field.appearance is not None and trainer.weights.averaged is not None
    return trainer


def view(trainer: Trainer, i: int = 0) -> dict:
    split = trainer.scene.test
    return dict(c2w=split.c2w[i], intrinsics=split.intrinsics[i], width=split.width, height=split.height)


def render(trainer: Trainer, code: torch.Tensor | None, i: int = 0) -> torch.Tensor:
    return trainer.render_image(**view(trainer, i), background=0.0, supersample=1, appearance_code=code)["rgb"]


def test_fitted_code_reproduces_a_known_code_and_leaves_the_field_alone(trained):
    field = trained.field
    mean = field.appearance.weight.detach().mean(0)
    known = mean + 2.0 * torch.randn(mean.shape, generator=torch.Generator().manual_seed(7))
    target = render(trained, known)
    weights = [p.detach().clone() for p in field.parameters()]
    averaged = [a.clone() for a in trained.weights.averaged]
    code = fit_appearance_code(trained, **view(trained), image=target, background=0.0, **FIT)
    assert code.shape == mean.shape and code.dtype == torch.float32 and not code.requires_grad
    with_mean = psnr(right_half(render(trained, None)), right_half(target))
    fitted = psnr(right_half(render(trained, code)), right_half(target))
    assert fitted > with_mean + 10.0, (with_mean, fitted)  # the code itself is not unique: 16 numbers, 3 colours
    assert all(torch.equal(a, b) for a, b in zip(weights, field.parameters(), strict=True))
    assert all(torch.equal(a, b) for a, b in zip(averaged, trained.weights.averaged, strict=True))
    assert all(p.grad is None for p in field.parameters())


def fit_by_rendering_each_iteration(trainer, c2w, intrinsics, width, height, image, background, iterations,
                                    rays_per_iteration, lr=1e-2, seed=0, pull=0.0):
    """The fit as its definition reads: every iteration renders its rays anew with the code, its
    loss the squared error plus ``pull`` times the code's mean squared distance to the mean code."""
    from ngp_warp.data.cameras import generate_rays
    from ngp_warp.ops.optim import Adam
    from ngp_warp.training.appearance_fit import _left_half_pixels

    field = trainer.field
    px_all, py_all = _left_half_pixels(width, height, iterations, rays_per_iteration, seed)
    with trainer.weights.averaged_in_field():
        mean = field.appearance.weight.detach().mean(0)
        code = mean.clone().requires_grad_(True)
        adam = Adam([code], lr=lr)

        def field_fn(positions, directions):
            sigma, h = field.geometry(positions)
            return sigma, field.colour(h, directions, code, differentiable=True)

        for px, py in zip(px_all, py_all):
            n = px.shape[0]
            rays_o, rays_d = generate_rays(c2w[None].expand(n, 3, 4), intrinsics[None].expand(n, 4), None, px, py)
            out = trainer.model.render(rays_o, rays_d, field_fn, background=background, sigma_fn=field.density)
            if out["n_samples"] == 0:
                continue
            loss = (out["rgb"] - image[py, px]).square().mean() + pull * (code - mean).square().mean()
            (code.grad,) = torch.autograd.grad(loss, [code])
            adam.step()
    return code.detach()


@pytest.mark.parametrize("group_rays,pull", [(1 << 16, 0.0), (48, 0.0), (1 << 16, 0.05)])  # one group; a group
def test_fit_from_kept_samples_equals_rendering_every_iteration(trained, monkeypatch, group_rays, pull):  # of one iteration
    import ngp_warp.training.appearance_fit as appearance_fit

    monkeypatch.setattr(appearance_fit, "FIT_GROUP_RAYS", group_rays)
    mean = trained.field.appearance.weight.detach().mean(0)
    known = mean + 2.0 * torch.randn(mean.shape, generator=torch.Generator().manual_seed(3))
    target = render(trained, known)
    fitted = fit_appearance_code(trained, **view(trained), image=target, background=0.5, iterations=25,
                                 rays_per_iteration=40, seed=5, pull=pull)
    want = fit_by_rendering_each_iteration(trained, **view(trained), image=target, background=0.5, iterations=25,
                                           rays_per_iteration=40, seed=5, pull=pull)
    assert (fitted - mean).norm() > 0.02  # it moved
    torch.testing.assert_close(fitted, want, rtol=0, atol=1e-4)


def test_fit_sees_only_the_left_half_and_is_deterministic(trained):
    target = render(trained, None) * 0.7  # darker than any code renders with the mean
    code = fit_appearance_code(trained, **view(trained), image=target, background=0.0, **FIT)
    noisy = target.clone()
    noisy[:, target.shape[1] // 2:] = torch.rand_like(noisy[:, target.shape[1] // 2:])
    assert torch.equal(fit_appearance_code(trained, **view(trained), image=noisy, background=0.0, **FIT), code)
    left = target.clone()
    left[:, : target.shape[1] // 2 - 1] = torch.rand_like(left[:, : target.shape[1] // 2 - 1])
    assert not torch.equal(fit_appearance_code(trained, **view(trained), image=left, background=0.0, **FIT), code)


def test_the_fit_starts_from_the_code_given(trained):
    with trained.weights.averaged_in_field():  # the fit renders with the weight average, its codes too
        codes = trained.field.appearance.weight.detach().clone()
    target = render(trained, codes[3])
    still = dict(image=target, background=0.0, iterations=1, lr=1e-9)  # one step too small to move it
    assert torch.allclose(fit_appearance_code(trained, **view(trained), **still), codes.mean(0), atol=1e-6)
    assert torch.allclose(fit_appearance_code(trained, **view(trained), **still, start=codes[3]), codes[3], atol=1e-6)
    with pytest.raises(ValueError, match="start must be one code of"):
        fit_appearance_code(trained, **view(trained), **still, start=codes[:2])


def test_the_pull_holds_the_code_toward_its_start(trained):
    with trained.weights.averaged_in_field():
        codes = trained.field.appearance.weight.detach().clone()
    start = codes[3]
    known = start + 2.0 * torch.randn(start.shape, generator=torch.Generator().manual_seed(11))
    fit = dict(image=render(trained, known), background=0.0, start=start, **FIT)
    distance = [(fit_appearance_code(trained, **view(trained), **fit, pull=pull) - start).norm().item()
                for pull in (0.0, 0.01, 1e4)]
    assert distance[0] > distance[1] > 0.0 and distance[2] < 0.05 * distance[0], distance
    for bad in (-1.0, float("nan"), float("inf"), True, "0.1"):
        with pytest.raises(ValueError, match="pull must be a finite number"):
            fit_appearance_code(trained, **view(trained), **fit, pull=bad)


def test_random_batches_are_seeded(trained):
    target = render(trained, None) * 0.7
    fit = dict(image=target, background=0.0, iterations=20, rays_per_iteration=64)  # fewer than 288 pixels
    first = fit_appearance_code(trained, **view(trained), **fit, seed=1)
    torch.rand(3)  # the global generator plays no part
    assert torch.equal(fit_appearance_code(trained, **view(trained), **fit, seed=1), first)
    assert not torch.equal(fit_appearance_code(trained, **view(trained), **fit, seed=2), first)


def test_right_half_is_the_columns_from_the_middle():
    image = torch.arange(5 * 7 * 3, dtype=torch.float32).reshape(5, 7, 3)
    assert torch.equal(right_half(image), image[:, 3:])


def test_mistakes_are_one_line(trained, tmp_path):
    target = render(trained, None)
    with pytest.raises(ValueError, match=r"image must be a float \[24, 24, 3\]"):
        fit_appearance_code(trained, **view(trained), image=target[:, :20])
    with pytest.raises(ValueError, match="iterations"):
        fit_appearance_code(trained, **view(trained), image=target, iterations=0)
    path = write_demo_scene(tmp_path / "scene", width=16, height=16, n_train=4, n_test=1, supersample=1)
    synthetic = Trainer(load_scene(path), small_config(1), device="cpu")
    with pytest.raises(ValueError, match="appearance codes"):
        fit_appearance_code(synthetic, **view(synthetic), image=torch.rand(16, 16, 3))


def test_evaluation_scores_the_right_half_with_the_fitted_code(trained, tmp_path):
    metrics = evaluate(trained, tmp_path, show_progress=False)
    assert metrics["appearance"].startswith(f"code fitted on the left half ({FIT_ITERATIONS} iterations from the "
                                            f"nearest training camera's code, pulled toward it with weight "
                                            f"{FIT_PULL:g}), scored on the right half; whole images with the nearest")
    assert json.loads((tmp_path / "metrics.json").read_text())["appearance"] == metrics["appearance"]
    fitted = list(iter_test_renders(trained, fit_appearance=True))
    mean_code = list(iter_test_renders(trained))
    nearest = list(iter_test_renders(trained, nearest_code=True))
    for i, (record, (name, out, gt), (_, mean_out, _), (_, near_out, _)) in enumerate(zip(
            metrics["per_image"], fitted, mean_code, nearest, strict=True)):
        assert record["image"] == name and out["appearance_code"].shape == (16,)
        camera = view(trained, i)
        from_nearest = fit_appearance_code(trained, **camera, image=gt, background=trained.view_background,
                                           start=nearest_training_code(trained, camera["c2w"]))
        assert torch.equal(out["appearance_code"], from_nearest)  # fitted from, and pulled toward, the nearest
        assert record["psnr"] == pytest.approx(psnr(right_half(out["rgb"]), right_half(gt)), abs=1e-9)
        assert record["psnr_mean_code"] == pytest.approx(psnr(mean_out["rgb"], gt), abs=1e-9)
        assert record["psnr_nearest_code"] == pytest.approx(psnr(near_out["rgb"], gt), abs=1e-9)
        half = gt.shape[1] // 2
        assert record["psnr_nearest_code_left"] == pytest.approx(psnr(near_out["rgb"][:, :half], gt[:, :half]), abs=1e-9)
        assert record["psnr_nearest_code_right"] == pytest.approx(psnr(near_out["rgb"][:, half:], gt[:, half:]),
                                                                  abs=1e-9)
        assert record["psnr_nearest_code_left"] != record["psnr_nearest_code_right"]
        assert not torch.equal(near_out["rgb"], mean_out["rgb"])  # another code than the mean
        assert "appearance_code" not in mean_out
        written = torch.from_numpy(iio.imread(tmp_path / "renders" / f"{Path(name).stem}.png"))
        assert torch.equal(written, to_uint8(out["rgb"]))
    for key in ("psnr_mean_code", "psnr_nearest_code_left", "psnr_nearest_code_right"):
        assert metrics[key] == pytest.approx(sum(m[key] for m in metrics["per_image"]) / 2)
    assert metrics["ssim"] is not None  # the right half (24 x 12) holds an SSIM window


def test_the_nearest_code_is_the_nearest_training_cameras(trained):
    split = trained.train_split
    for k in (0, len(split) - 1):
        c2w = split.c2w[k].clone()
        c2w[:3, 3] += 1e-3  # beside training camera k
        torch.testing.assert_close(nearest_training_code(trained, c2w), trained.field.appearance.weight[k].detach())


def test_evaluation_without_codes_keeps_its_keys(tmp_path):
    path = write_demo_scene(tmp_path / "scene", width=16, height=16, n_train=4, n_test=1, supersample=1)
    trainer = Trainer(load_scene(path), small_config(1), device="cpu")
    metrics = evaluate(trainer, tmp_path, show_progress=False)
    assert set(metrics) == {"psnr", "ssim", "lpips", "lpips_note", "train_seconds", "steps", "train_samples_per_ray",
                            "device", "test_split",
                            "n_test_images", "per_image"}
    assert set(metrics["per_image"][0]) == {"image", "psnr", "ssim", "lpips"}
    (record,), (name, view, truth) = metrics["per_image"], next(iter_test_renders(trainer))
    assert record["image"] == name and type(record["psnr"]) is float and type(record["ssim"]) is float
    assert record["psnr"] == pytest.approx(psnr(view["rgb"], truth), abs=1e-9)
    assert record["ssim"] == pytest.approx(ssim(view["rgb"], truth), abs=1e-12)
    written = torch.from_numpy(iio.imread(tmp_path / "depth" / f"{Path(name).stem}.png"))
    assert torch.equal(written, depth_to_uint8(view["depth"], view["opacity"]))
    _, out, gt = next(iter_test_renders(trainer, fit_appearance=True))  # no codes: nothing fitted
    assert "appearance_code" not in out and out["rgb"].shape == gt.shape
