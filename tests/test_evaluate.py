"""The evaluation's image conversions (depth maps as uint8) and its waits for the device."""

import threading
import warnings

import numpy as np
import pytest
import torch

from ngp_warp.data.loading import load_scene
from ngp_warp.data.scene import write_demo_scene
from ngp_warp.ops.field import FieldConfig
from ngp_warp.outputs.evaluate import (NEAREST_CODE_KEYS, _groups, _GroupReadout, _one_behind, depth_to_uint8, evaluate,
                                       psnr_whole_and_halves, score_group_size, to_uint8)
from ngp_warp.outputs.metrics import psnr_tensor, ssim_tensor
from ngp_warp.training.appearance_fit import right_half
from ngp_warp.training.config import TrainConfig
from ngp_warp.training.trainer import Trainer


def test_depth_spans_the_opaque_pixels_near_bright():
    gen = torch.Generator().manual_seed(0)
    depth = 0.5 + 4 * torch.rand(24, 32, generator=gen)
    opacity = torch.rand(24, 32, generator=gen)
    img = depth_to_uint8(depth * opacity, opacity).numpy()  # the renderer's depth is weighted by opacity
    opaque = (opacity > 0.5).numpy()
    d = depth.numpy()
    want = 1.0 - (d - d[opaque].min()) / (d[opaque].max() - d[opaque].min())
    want = np.where(opaque, np.floor(want * 255 + 0.5), 0)
    assert img.dtype == np.uint8 and img.shape == (24, 32)
    assert np.abs(img.astype(int) - want).max() <= 1  # float32 rounding at .5
    assert img[opaque].max() == 255 and img[opaque].min() == 0 and (img[~opaque] == 0).all()


def test_depth_of_a_transparent_view_is_black():
    depth = torch.rand(8, 8) * 3
    assert (depth_to_uint8(depth, torch.full((8, 8), 0.2)) == 0).all()


def test_each_view_is_read_once_the_next_has_been_made():
    made = []

    def views():
        for i in range(3):
            made.append(i)
            yield i

    assert [(i, list(made)) for i in _one_behind(views())] == [(0, [0, 1]), (1, [0, 1, 2]), (2, [0, 1, 2])]
    assert list(_one_behind(iter(()))) == [] and list(_one_behind([None])) == [None]


def _random_views(n: int, height: int, width: int, fitted: bool) -> list:
    gen = torch.Generator().manual_seed(n + height)
    views = []
    for k in range(n):
        out = {"rgb": torch.rand(height, width, 3, generator=gen), "depth": torch.rand(height, width, generator=gen),
               "opacity": torch.rand(height, width, generator=gen)}
        if fitted:
            out["other_rgb"] = torch.rand(2, height, width, 3, generator=gen)
        views.append((f"v{k}.png", out, torch.rand(height, width, 3, generator=gen)))
    return views


@pytest.mark.parametrize("fitted", [False, True])
@pytest.mark.parametrize("size", [(12, 26), (9, 10)])  # the second below SSIM's window: no SSIM
def test_a_group_of_views_scores_and_reads_as_each_view_alone(fitted, size):
    views = _random_views(3, *size, fitted)
    looked = []
    read = _GroupReadout(views, fitted, lambda rgb, gt: looked.append(rgb.shape) or (None, "no lpips")).read()
    assert [name for name, *_ in read] == ["v0.png", "v1.png", "v2.png"] and len(looked) == 3
    for (name, scores, rgb, depth), (_, out, gt) in zip(read, views):
        pred, ref = (right_half(out["rgb"]), right_half(gt)) if fitted else (out["rgb"], gt)
        want = {"psnr": psnr_tensor(pred, ref).item(),
                "ssim": ssim_tensor(pred, ref).item() if min(size) >= 11 else None, "lpips": None}
        if fitted:
            nearest, mean = out["other_rgb"]
            want["psnr_mean_code"] = psnr_tensor(mean, gt).item()
            want.update(zip(NEAREST_CODE_KEYS, (t.item() for t in psnr_whole_and_halves(nearest, gt))))
        assert list(scores) == list(want)  # metrics.json's order
        assert scores == pytest.approx(want, rel=1e-12)
        assert np.array_equal(rgb, to_uint8(out["rgb"]).numpy())
        assert np.array_equal(depth, depth_to_uint8(out["depth"], out["opacity"]).numpy())


def test_views_are_scored_in_groups_of_a_few_million_pixels():
    assert score_group_size(400, 400) == 8 and score_group_size(1920, 1080) == 1 and score_group_size(800, 800) == 3
    assert [len(g) for g in _groups(range(19), 8)] == [8, 8, 3] and list(_groups([], 8)) == []


def _host_waits(work) -> int:
    """How often ``work()`` made the host wait for the device (torch's sync debug mode)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            work()
        finally:
            torch.cuda.set_sync_debug_mode("default")
    return sum("synchroniz" in str(w.message) for w in caught)


@pytest.mark.cuda
def test_the_evaluation_waits_for_the_device_only_where_its_renders_do(tmp_path):
    path = write_demo_scene(tmp_path / "scene", width=32, height=32, n_train=4, n_test=4, supersample=1, device="cuda")
    config = TrainConfig(steps=30, target_samples=1 << 13, grid_resolution=32,
                         field=FieldConfig(n_levels=8, log2_hashmap_size=14, hidden=32))
    trainer = Trainer(load_scene(path), config, device="cuda")
    trainer.train(show_progress=False)
    evaluate(trainer, tmp_path, show_progress=False)  # kernels loaded, the renderer's guesses settled
    split = trainer.scene.test
    cameras = [{**split.camera(i), "c2w": split.c2w[i].cuda(), "intrinsics": split.intrinsics[i].cuda()}
               for i in range(len(split))]
    renders = _host_waits(lambda: [trainer.render_image(**camera) for camera in cameras])
    whole = _host_waits(lambda: evaluate(trainer, tmp_path, show_progress=False))
    print(f"host waits: renders {renders}, evaluation {whole}")
    # a view's scores, render and depth map read once the next view is queued; a few waits in all beside
    assert renders > 0 and whole <= renders + 3 * len(cameras) + 6


def test_an_evaluation_looks_up_lpips_once(tmp_path, monkeypatch):
    from ngp_warp.outputs import lpips

    looked_up = []
    monkeypatch.setattr(lpips, "unavailable_reason", lambda net: looked_up.append(net) or "not here")
    path = write_demo_scene(tmp_path / "scene", width=16, height=16, n_train=4, n_test=3, supersample=1)
    config = TrainConfig(steps=1, target_samples=1 << 10, grid_resolution=16,
                         field=FieldConfig(n_levels=4, log2_hashmap_size=12, hidden=16))
    metrics = evaluate(Trainer(load_scene(path), config, device="cpu"), tmp_path, show_progress=False)
    assert len(metrics["per_image"]) == 3 and looked_up == ["alex"]
    assert metrics["lpips"] is None and metrics["lpips_note"] == "not computed: not here"


def test_a_weight_average_block_inside_another_leaves_the_field_alone(tmp_path):
    path = write_demo_scene(tmp_path / "scene", width=16, height=16, n_train=4, n_test=1, supersample=1)
    config = TrainConfig(steps=30, target_samples=1 << 12, grid_resolution=16,
                         field=FieldConfig(n_levels=4, log2_hashmap_size=12, hidden=16))
    trainer = Trainer(load_scene(path), config, device="cpu")
    trainer.train(show_progress=False)
    table = next(trainer.field.encoding.parameters())
    live, seen = table.detach().clone(), []
    with trainer.weights.averaged_in_field():
        assert not torch.equal(table, live)  # the average in
        with torch.no_grad():
            table.add_(1.0)  # weights an inner block must leave as they are (an evaluation's renders)
        marked = table.detach().clone()

        def inner():
            with trainer.weights.averaged_in_field():
                seen.append(torch.equal(table, marked))

        worker = threading.Thread(target=inner)
        worker.start()
        worker.join()
        seen.append(torch.equal(table, marked))
    assert seen == [True, True] and torch.equal(table, live)


def test_background_writes_use_their_threads_wait_for_every_write_and_raise_the_first_failure(monkeypatch):
    import ngp_warp.outputs.evaluate as evaluate_module

    assert 2 <= evaluate_module.write_workers() <= 6
    monkeypatch.setattr(evaluate_module, "cpu_threads", lambda: 64)
    assert evaluate_module.write_workers() == 6  # half the cores, at most 6
    monkeypatch.setattr(evaluate_module, "cpu_threads", lambda: 8)
    assert evaluate_module.write_workers() == 4
    monkeypatch.setattr(evaluate_module, "cpu_threads", lambda: 1)
    assert evaluate_module.write_workers() == 2

    written, threads, all_in = [], set(), threading.Barrier(3, timeout=30)

    def write(k):
        if k < 3:
            all_in.wait()  # three writes at once: three threads
        threads.add(threading.current_thread().name)
        written.append(k)

    with evaluate_module.BackgroundWrites(workers=3) as writes:
        for k in range(20):  # more than the queue holds (12): submit waits for the oldest
            writes.submit(write, k)
    assert sorted(written) == list(range(20)) and len(threads) == 3

    def fails(k):
        raise OSError(f"disk full at {k}")

    with pytest.raises(OSError, match="disk full at 0"):
        with evaluate_module.BackgroundWrites(workers=2) as writes:
            writes.submit(fails, 0)
