"""End-to-end training on a tiny generated scene (CPU), settings, and the step's parts
(checkpoints: test_checkpoint.py)."""

import dataclasses
import math
from collections import Counter

import pytest
import torch

from ngp_warp.training.config import TrainConfig, apply_overrides, device_defaults, pixel_matched_resolution
from ngp_warp.data.loading import load_scene
from ngp_warp.outputs.evaluate import iter_test_renders
from ngp_warp.ops.field import FieldConfig
from ngp_warp.outputs.metrics import psnr
from ngp_warp.data.scene import CAMERA_ANGLE_X, CAMERA_RADIUS, write_demo_scene
from ngp_warp.training.train_step import HostCopy, StepPhases
from ngp_warp.training.trainer import Trainer


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    path = tmp_path_factory.mktemp("scene") / "demo"
    write_demo_scene(path, width=32, height=32, n_train=24, n_test=3, supersample=2)
    return path


def tiny_config(steps: int) -> TrainConfig:
    return TrainConfig(steps=steps, target_samples=1 << 13, grid_resolution=32, steps_per_diagonal=256,
                       field=FieldConfig(n_levels=8, log2_hashmap_size=14, finest_resolution=128.0, hidden=32))


def mean_psnr(trainer: Trainer) -> float:
    scores = [psnr(out["rgb"], gt) for _, out, gt in iter_test_renders(trainer)]
    return sum(scores) / len(scores)


def test_training_raises_held_out_psnr(tiny_scene):
    trainer = Trainer(load_scene(tiny_scene), tiny_config(300), device="cpu")
    before = mean_psnr(trainer)
    trainer.train(show_progress=False)
    after = mean_psnr(trainer)
    assert trainer.step_count == 300
    assert after > before + 8.0, (before, after)
    assert after > 20.0


def test_training_is_reproducible(tiny_scene):
    runs = []
    for _ in range(2):
        trainer = Trainer(load_scene(tiny_scene), tiny_config(15), device="cpu")
        trainer.train(show_progress=False)
        runs.append(trainer.field.encoding.params.detach().clone())
    torch.testing.assert_close(runs[0], runs[1], rtol=0, atol=1e-6)


def test_deferred_optimizer_updates_equal_updates_at_the_end_of_each_step(tiny_scene):
    # step() leaves its update to the next step's march (while the host waits for the count);
    # flushing after every step is the plain order. 20 steps cross a grid refresh (step 16),
    # the lr warm-up and the weight average's decay schedule.
    def train(flush_each_step: bool) -> list[torch.Tensor]:
        trainer = Trainer(load_scene(tiny_scene), tiny_config(20), device="cpu")
        mlp_adam = trainer.weights.mlp_adam
        mlp_step, lrs = mlp_adam.step, []

        def recording_step(*args, **kwargs):  # each update's lr: the schedule's at its own step
            lrs.append(mlp_adam.param_groups[0]["lr"])
            return mlp_step(*args, **kwargs)

        mlp_adam.step = recording_step
        for _ in range(20):
            trainer.step(progress=trainer.step_count / 20)
            assert trainer.weights.pending  # the update waits for the next step
            if flush_each_step:
                trainer.flush()
        trainer.flush()
        schedule = [1e-2 * min(1.0, 0.01 + k / 100) * 0.33 ** sum(k / 20 >= m for m in (0.5, 0.75, 0.9))
                    for k in range(20)]
        assert lrs == pytest.approx(schedule, rel=1e-12)
        return [p.detach().clone() for p in trainer.field.parameters()] + \
            [a.clone() for a in trainer.averaged_weights()] + [trainer.grid.occs.clone()]

    deferred, plain = train(False), train(True)
    for a, b in zip(deferred, plain, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    start = Trainer(load_scene(tiny_scene), tiny_config(20), device="cpu").field.encoding.params
    assert not torch.equal(start, deferred[0])  # the updates were applied


def test_instrumented_phases_see_every_call_and_change_nothing(tiny_scene):
    calls = Counter()

    def counting(phase, fn):
        def call(*args, **kwargs):
            calls[phase] += 1
            return fn(*args, **kwargs)
        return call

    def train(instrument: bool) -> Trainer:  # each from the seed: the march's jitter draws from torch's RNG
        trainer = Trainer(load_scene(tiny_scene), apply_overrides(tiny_config(20), ["distortion_weight=0.1"]),
                          device="cpu")  # every phase runs
        if instrument:
            trainer.instrument(counting)
        trainer.train(show_progress=False)
        return trainer

    plain, counted = train(False), train(True)
    for a, b in zip(plain.field.parameters(), counted.field.parameters(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert set(calls) == {f.name for f in dataclasses.fields(StepPhases)}
    once_a_step = ("grid_update", "sample_batch", "render", "field", "loss", "distortion", "backward")
    assert all(calls[phase] == 20 for phase in once_a_step), calls
    # the density pass before each pruning, plus the grid refresh's chunks (steps 0 and 16)
    assert calls["density"] > 20
    # once in each march, in the refreshes, and train()'s final flush
    assert calls["optimizer_update"] >= 21


def test_table_average_kept_lazily_equals_a_dense_average_of_the_table(tiny_scene):
    trainer = Trainer(load_scene(tiny_scene), tiny_config(25), device="cpu")
    opt, table = trainer.weights.table_adam, trainer.field.encoding.params
    start = table.detach().double().clone()
    trajectory = []  # (decay, table after the step) per step
    step = opt.step
    mlp = trainer.field.mlp_parameters()
    mlp_trajectory = []  # the MLP's weights after each step

    def recording_step(*args, **kwargs):
        result = step(*args, **kwargs)
        trajectory.append((opt.param_groups[0]["average_decay"], table.detach().double().clone()))
        return result

    mlp_step = trainer.weights.mlp_adam.step

    def recording_mlp_step(*args, **kwargs):
        result = mlp_step(*args, **kwargs)
        mlp_trajectory.append([p.detach().double().clone() for p in mlp])
        return result

    mlp_start = [p.detach().double().clone() for p in mlp]
    opt.step, trainer.weights.mlp_adam.step = recording_step, recording_mlp_step
    trainer.train(show_progress=False)
    decays = [min(0.995, (1 + s) / (10 + s)) for s in range(25)]  # the trainer's schedule
    assert [d for d, _ in trajectory] == pytest.approx(decays)
    dense, mlp_dense = start, mlp_start
    for decay, weights, mlp_weights in zip(decays, (w for _, w in trajectory), mlp_trajectory, strict=True):
        dense = torch.lerp(dense, weights, 1 - decay)
        mlp_dense = [torch.lerp(a, w, 1 - decay) for a, w in zip(mlp_dense, mlp_weights)]
    assert (dense - table.double()).abs().max() > 1e-4
    assert not any(a.requires_grad for a in trainer.weights.averaged)  # averaging stays out of autograd
    averaged = dict(zip(map(id, trainer.field.parameters()), trainer.averaged_weights()))
    torch.testing.assert_close(averaged[id(table)].double(), dense, rtol=0, atol=1e-6)
    for p, expected in zip(mlp, mlp_dense, strict=True):
        torch.testing.assert_close(averaged[id(p)].double(), expected, rtol=0, atol=1e-6)


def test_render_image_averages_jittered_renders(tiny_scene):
    trainer = Trainer(load_scene(tiny_scene), tiny_config(60), device="cpu")
    trainer.train(show_progress=False)
    split = trainer.scene.test
    one, four = (trainer.render_image(split.c2w[0], split.intrinsics[0], split.width, split.height, spp=k)
                 for k in (1, 4))
    assert not torch.equal(one["rgb"], four["rgb"])  # jittered offsets moved the samples
    assert psnr(four["rgb"], one["rgb"]) > 25.0  # ... but render the same picture
    with pytest.raises(ValueError, match="spp"):
        trainer.render_image(split.c2w[0], split.intrinsics[0], 4, 4, spp=0)


def test_settings_override_a_copy_of_the_config(tiny_scene):
    base = TrainConfig()
    cfg = apply_overrides(base, ["loss=huber", "seconds=60", "prune=false", "field.finest_resolution=1024"])
    assert (cfg.loss, cfg.seconds, cfg.prune, cfg.field.finest_resolution) == ("huber", 60, False, 1024.0)
    assert (base.loss, base.seconds, base.prune, base.field.finest_resolution) == ("l2", None, True, None)
    boxes = [apply_overrides(base, [f"aabb_scale={text}"]).aabb_scale for text in ("auto", "none", "8", "3")]
    assert boxes == ["auto", None, 8, 3]
    with pytest.raises(ValueError, match="aabb_scale must be auto, none or a power of two"):
        apply_overrides(base, ["aabb_scale=3"]).check()
    assert apply_overrides(cfg, ["field.finest_resolution=none"]).field.finest_resolution is None
    for bad, message in [("nope=1", "unknown setting"), ("nope", "unknown setting"), ("loss", "loss has no value"),
                         ("field.hidden", "field.hidden has no value; write field.hidden=VALUE"),
                         ("field.hidden=x", "an integer"), ("prune=maybe", "true or false")]:
        with pytest.raises(ValueError, match=message):
            apply_overrides(base, [bad])
    with pytest.raises(ValueError, match="mlp_precision"):
        Trainer(load_scene(tiny_scene), apply_overrides(base, ["mlp_precision=fp8"]), device="cpu")


@pytest.mark.cuda
@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_cuda_graph_field_matches_the_eager_field(tiny_scene, precision):
    cfg = apply_overrides(tiny_config(20), [f"mlp_precision={precision}"])
    trainer = Trainer(load_scene(tiny_scene), cfg, device="cuda")
    trainer.train(show_progress=False)
    assert trainer.training_field.graphed_forward is not None  # training went through the captured graphs
    assert trainer.field.forward.__func__ is type(trainer.field).forward  # the field itself stays eager
    n, field = trainer.target_samples, trainer.field
    g = torch.Generator(device="cuda").manual_seed(0)
    lo, hi = field.aabb[:3], field.aabb[3:]
    positions = lo + (hi - lo) * torch.rand(n, 3, device="cuda", generator=g)
    directions = torch.nn.functional.normalize(torch.randn(n, 3, device="cuda", generator=g), dim=-1)
    w_sigma, w_rgb = torch.randn(n, device="cuda", generator=g), torch.randn(n, 3, device="cuda", generator=g)

    def values_and_grads(fn):
        field.zero_grad(set_to_none=True)
        sigma, rgb = fn(positions, directions)
        ((sigma * w_sigma).sum() + (rgb * w_rgb).sum()).backward()
        return [sigma.detach().clone(), rgb.detach().clone()] + [p.grad.clone() for p in field.parameters()]

    with trainer.model.precision():  # as in training: bf16 matmuls under autocast
        eager = values_and_grads(field)
        graphed = values_and_grads(trainer.training_field)
    assert eager[-1].abs().max() > 0
    # bf16: cuBLAS may pick another kernel inside the capture, so allow a few bf16 roundings
    tol = dict(rtol=1e-4, atol=1e-6) if precision == "fp32" else dict(rtol=3e-2, atol=1e-3)
    for a, b in zip(eager, graphed):
        torch.testing.assert_close(b, a, **tol)


def test_finest_resolution_follows_the_training_pixels(tiny_scene):
    # Demo cameras look at the box centre from CAMERA_RADIUS; a pixel there is radius / fx wide.
    scene = load_scene(tiny_scene)
    side = float((scene.aabb[3:] - scene.aabb[:3]).max())
    fx = 0.5 * scene.train.width / math.tan(0.5 * CAMERA_ANGLE_X)
    assert pixel_matched_resolution(scene) == max(64, round(side * fx / CAMERA_RADIUS))
    scene.train.intrinsics = scene.train.intrinsics * 20  # a 20× sharper camera: 20× finer cells
    assert pixel_matched_resolution(scene) == round(side * 20 * fx / CAMERA_RADIUS)
    scene.train.intrinsics = scene.train.intrinsics * 1000  # capped at instant-ngp's 2048
    assert pixel_matched_resolution(scene) == 2048.0


@pytest.mark.parametrize("device,sub", [("cuda", 2), ("cpu", 1)])
def test_unset_supersample_follows_the_device(device, sub):
    assert TrainConfig().supersample is None and device_defaults(TrainConfig(), device).supersample == sub
    assert device_defaults(TrainConfig(supersample=3), device).supersample == 3
    cfg = TrainConfig()
    assert cfg.field.log2_hashmap_size == 19  # instant-ngp's on both devices
    assert cfg.distortion_weight is None  # per scene (test_scene_defaults)


@pytest.mark.parametrize("setting", ["steps=0", "seconds=-1", "target_samples=0", "grid_resolution=0", "lr=-1e-3",
                                     "cone_angle=-0.1", "weight_average=1", "supersample=0", "mlp_precision=fp16",
                                     "occupancy_threshold=0", "occupancy_decay=1", "occupancy_decay=-0.5", "near=0", "near=-1", "near=1e5"])
def test_config_check_names_the_setting_out_of_range(setting):
    cfg = apply_overrides(TrainConfig(), [setting])
    with pytest.raises(ValueError, match=setting.split("=")[0]):
        cfg.check()
    TrainConfig().check()  # the defaults, None included, pass


@pytest.mark.parametrize("bad", [dict(supersample=2.0), dict(supersample=True), dict(steps=2.5), dict(lr=True),
                                 dict(field=FieldConfig(n_levels=0)), dict(field=FieldConfig(log2_hashmap_size=31)),
                                 dict(field=FieldConfig(n_features_per_level=3)),
                                 dict(field=FieldConfig(finest_resolution=-1.0)), dict(distortion_weight="0"),
                                 dict(field=FieldConfig(log2_hashmap_size=None))])
def test_config_check_refuses_wrong_types_and_field_sizes(bad):
    with pytest.raises(ValueError, match="must be"):
        TrainConfig(**bad).check()


def test_occupancy_settings_reach_the_grid(tiny_scene):
    """A higher occupancy threshold leaves fewer cells occupied after the same steps (one step with a
    refresh, from the same weights: the grid's own update rule, min(threshold, mean), decides)."""
    scene = load_scene(tiny_scene)
    assert scene.source == "nerf-synthetic" and Trainer(scene, tiny_config(1), device="cpu").config.occupancy_threshold == 0.01
    occupied = {}
    for threshold in (1e-4, 10.0):
        cfg = tiny_config(1)
        cfg.occupancy_threshold, cfg.occupancy_decay = threshold, 0.5
        trainer = Trainer(scene, cfg, device="cpu")
        trainer.step()
        occupied[threshold] = int(trainer.grid.occupied().sum())
        assert float(trainer.grid.threshold) <= threshold
    assert occupied[10.0] < occupied[1e-4]


@pytest.mark.parametrize("prune", [True, False])
def test_step_reports_marched_and_trained_sample_counts(tiny_scene, prune):
    cfg = tiny_config(30)
    cfg.prune = prune
    trainer = Trainer(load_scene(tiny_scene), cfg, device="cpu")
    trainer.train(show_progress=False)
    stats = trainer.step()
    assert isinstance(stats["marched"], int) and isinstance(stats["samples"], int)
    if prune:  # trained on: the marched samples that composite (all of them, early on)
        assert stats["marched"] >= stats["samples"] > 0
    else:
        assert stats["marched"] == stats["samples"] > 0


def test_distortion_weight_adds_the_distortion_loss(tiny_scene):
    cfg = tiny_config(3)
    cfg.distortion_weight = 0.5
    trainer = Trainer(load_scene(tiny_scene), cfg, device="cpu")
    trainer.train(show_progress=False)
    stats = trainer.step()
    assert float(stats["loss"]) > float(stats["mse"]) > 0


def test_supersampled_training_fits_pixels_as_means_of_sub_rays(tiny_scene):
    cfg = apply_overrides(tiny_config(300), ["supersample=2"])
    trainer = Trainer(load_scene(tiny_scene), cfg, device="cpu")
    rays_o, rays_d, target, background = trainer.sample_batch(1000)
    assert rays_o.shape == rays_d.shape == (1000, 3) and target.shape == background.shape == (250, 3)
    before = mean_psnr(trainer)
    trainer.train(show_progress=False)
    assert mean_psnr(trainer) > before + 8.0
    camera = trainer.scene.test
    c2w, intr, w, h = camera.c2w[0], camera.intrinsics[0], camera.width, camera.height
    mean_of_four = trainer.render_image(c2w, intr, w, h)
    trainer.config = dataclasses.replace(trainer.config, supersample=1)
    centre = trainer.render_image(c2w, intr, w, h)
    assert (mean_of_four["rgb"] - centre["rgb"]).abs().mean() > 1e-3
    shifted = []  # a render through (px + 1/2 + dx, py + 1/2 + dy) is one with the principal point moved by −(dx, dy)
    for dx, dy in [(-0.25, -0.25), (0.25, -0.25), (-0.25, 0.25), (0.25, 0.25)]:
        moved = intr - torch.tensor([0.0, 0.0, dx, dy], dtype=intr.dtype)
        shifted.append(trainer.render_image(c2w, moved, w, h))
    for key in ("rgb", "opacity", "depth"):
        want = sum(r[key] for r in shifted) / 4
        torch.testing.assert_close(mean_of_four[key], want.clamp(0, 1) if key == "rgb" else want, atol=1e-5, rtol=1e-5)
    with pytest.raises(ValueError, match="supersample"):
        Trainer(load_scene(tiny_scene), apply_overrides(tiny_config(1), ["supersample=0"]), device="cpu")
    scene = load_scene(tiny_scene)
    scene.train.intrinsics = scene.train.intrinsics * 10  # clear of the 64-cell floor
    assert abs(pixel_matched_resolution(scene, 4) - 2 * pixel_matched_resolution(scene)) <= 1  # √4 × finer


def test_rays_start_where_a_render_asks(tiny_scene):
    trainer = Trainer(load_scene(tiny_scene), tiny_config(1), device="cpu")
    model, far = trainer.model, trainer.model.march.far
    for bad in (0.0, -1.0, far, far * 2):
        with pytest.raises(ValueError, match="near must be above 0 and below"):
            model.start_rays_at(bad)
    model.start_rays_at(2.0)
    assert model.march.near == 2.0 and model.march.far == far and not model.march.stratified
    assert model._stratified.near == 2.0 and model._stratified.stratified


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="no CUDA device"))])
def test_host_copy_reads_the_values_of_its_start_not_later_ones(device):
    gen = torch.Generator().manual_seed(3)
    values = torch.randn(2, generator=gen, dtype=torch.float64).to(device)
    copy = HostCopy(2, device)
    assert not copy.pending
    big = torch.randn(1024, 1024, generator=gen).to(device)
    loss = (big @ big).square().mean()  # queued work the copy lands behind
    copy.start(loss, values[1:])
    expected = [float(loss), float(values[1])]
    loss.fill_(-1.0)  # after the start: not in the copy
    assert copy.pending
    assert copy.read() == pytest.approx(expected, rel=1e-6) and not copy.pending
