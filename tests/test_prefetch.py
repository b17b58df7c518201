"""What a command starts while torch imports: a scene's images decoded by a child process
(ngp_warp.data.prefetch) and the CUDA driver's start (ngp_warp.cuda_start)."""

import os
import subprocess
import sys
import threading

import imageio.v3 as iio
import numpy as np
import pytest
from data_fixtures import instant_ngp, nerf_synthetic, random_image

from ngp_warp import cuda_start
from ngp_warp.cli import main
from ngp_warp.cli.train import prefetch_scene_images
from ngp_warp.data import images as images_module
from ngp_warp.data import prefetch
from ngp_warp.data.loading import DataError, load_scene


@pytest.fixture
def parent_reads(monkeypatch):
    """The image files the loading reads itself (not from the prefetch)."""
    read = []
    real = images_module.read_image
    monkeypatch.setattr(images_module, "read_image", lambda path: read.append(path.name) or real(path))
    yield read
    prefetch.drop_prefetched()


def _scene(tmp_path, **kwargs):
    nerf_synthetic(tmp_path / "s", n_train=4, n_test=3, size=(10, 7), **kwargs)
    return tmp_path / "s"


def _pixels(scene):
    return np.concatenate([scene.train.images.numpy().ravel(), scene.test.images.numpy().ravel()])


def test_the_loading_takes_every_image_from_the_child(tmp_path, parent_reads):
    scene = _scene(tmp_path)
    expected = _pixels(load_scene(scene))
    parent_reads.clear()
    assert prefetch.start_prefetch(scene, min_cores=1)
    got = load_scene(scene)
    assert parent_reads == []  # all 7 images came from the child's file
    assert np.array_equal(_pixels(got), expected)


def test_a_downscaled_instant_ngp_scene_loads_the_same(tmp_path, parent_reads):
    instant_ngp(tmp_path / "n", n=5, size=(12, 8))
    expected = _pixels(load_scene(tmp_path / "n", downscale=2))
    parent_reads.clear()
    assert prefetch.start_prefetch(tmp_path / "n", 2, min_cores=1)
    assert np.array_equal(_pixels(load_scene(tmp_path / "n", downscale=2)), expected)
    assert parent_reads == []


def test_a_file_changed_after_the_prefetch_is_read_again(tmp_path, parent_reads):
    scene = _scene(tmp_path)
    assert prefetch.start_prefetch(scene, min_cores=1)
    new = random_image(np.random.default_rng(9), 7, 10, 4)
    path = scene / "test" / "r_1.png"
    prefetch.read_prefetched(scene / "train" / "r_0.png")  # waits for the child
    iio.imwrite(path, new)
    os.utime(path, ns=(os.stat(path).st_atime_ns, os.stat(path).st_mtime_ns + 10**9))
    loaded = load_scene(scene)
    assert sorted(parent_reads) == ["r_0.png", "r_1.png"]  # the one taken above, and the changed file
    assert np.array_equal(loaded.test.images[1].numpy(), new)


def test_past_its_bytes_the_child_stops_and_the_loading_reads_the_rest(tmp_path, parent_reads):
    scene = _scene(tmp_path)  # 7 images of 10 × 7 RGBA: 280 bytes each
    expected = _pixels(load_scene(scene))
    parent_reads.clear()
    assert prefetch.start_prefetch(scene, min_cores=1, max_bytes=600)
    assert np.array_equal(_pixels(load_scene(scene)), expected)
    assert len(parent_reads) == 5
    assert prefetch._spool_dir(1 << 62) is None  # no /dev/shm that large: the temporary folder


def test_a_file_replaced_with_its_size_and_time_kept_is_read_again(tmp_path, parent_reads):
    scene = _scene(tmp_path)
    path = scene / "train" / "r_1.png"
    assert prefetch.start_prefetch(scene, min_cores=1)
    prefetch.collect_prefetched()
    before = os.stat(path)
    new = random_image(np.random.default_rng(3), 7, 10, 4)
    iio.imwrite(path, new)
    if os.stat(path).st_size != before.st_size:  # PNGs of random pixels: the same size, almost always
        pytest.skip("the new PNG's size differs")
    os.utime(path, ns=(before.st_atime_ns, before.st_mtime_ns))  # as `cp -p` or `rsync -t` leave it
    assert np.array_equal(load_scene(scene).train.images[1].numpy(), new)
    assert parent_reads == ["r_1.png"]


def test_an_interrupt_while_waiting_for_the_child_ends_it(tmp_path, monkeypatch):
    assert prefetch.start_prefetch(_scene(tmp_path), min_cores=1)
    child = prefetch._child[0]

    def interrupted():
        raise KeyboardInterrupt

    monkeypatch.setattr(child, "communicate", interrupted)
    with pytest.raises(KeyboardInterrupt):
        prefetch.collect_prefetched()
    assert child.poll() is not None and prefetch._child is None


def test_a_corrupt_file_raises_as_without_the_prefetch(tmp_path, parent_reads):
    scene = _scene(tmp_path)
    (scene / "train" / "r_2.png").write_bytes(b"not a png")
    with pytest.raises(DataError) as without:
        load_scene(scene)
    assert prefetch.start_prefetch(scene, min_cores=1)
    with pytest.raises(DataError) as with_it:
        load_scene(scene)
    assert str(with_it.value) == str(without.value) and "r_2.png" in str(with_it.value)


def test_a_child_that_fails_leaves_the_reading_to_the_loading(tmp_path, parent_reads, monkeypatch):
    scene = _scene(tmp_path)
    expected = _pixels(load_scene(scene))
    parent_reads.clear()
    with monkeypatch.context() as patched:
        patched.setattr(prefetch.sys, "executable", sys.executable + "-missing")
        assert not prefetch.start_prefetch(scene, min_cores=1)  # the child could not start
    assert prefetch.start_prefetch(tmp_path / "no such scene", min_cores=1)  # starts, lists nothing
    assert np.array_equal(_pixels(load_scene(scene)), expected)
    assert len(parent_reads) == 7


def test_dropped_or_too_few_cores_the_loading_reads_itself(tmp_path, parent_reads):
    scene = _scene(tmp_path)
    assert not prefetch.start_prefetch(scene, min_cores=prefetch.usable_cores() + 1)
    assert prefetch.start_prefetch(scene, min_cores=1)
    prefetch.drop_prefetched()
    load_scene(scene)
    assert len(parent_reads) == 7


def test_the_train_command_loads_its_scene_from_the_child(tmp_path, parent_reads, monkeypatch):
    scene = _scene(tmp_path)
    monkeypatch.setattr(prefetch, "MIN_CORES", 1)
    out = tmp_path / "run"
    assert main(["train", str(scene), "--out", str(out), "--steps", "2", "--no-video", "--device", "cpu", "--quiet",
                 "--target-samples", "4096"]) == 0
    assert parent_reads == [] and (out / "metrics.json").is_file()
    assert prefetch._child is None and prefetch._decoded is None  # dropped once the scene loaded


def test_the_command_line_starts_them_before_torch_and_warp_load():
    code = "import sys, ngp_warp.cli; print(*(m in sys.modules for m in ('torch', 'warp', 'numpy')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.stdout.split() == ["False", "False", "False"], out.stderr


@pytest.mark.parametrize("args, expected", [
    (["SCENE", "--out", "o"], [("SCENE", 1)]),
    (["SCENE", "--downscale", "4"], [("SCENE", 4)]),
    (["SCENE", "--downscale=2", "--device", "cuda"], [("SCENE", 2)]),
    (["SCENE", "--downscale", "0"], []),  # the parser refuses it
    (["SCENE", "--downscale", "²"], []),  # a digit to str.isdigit, not to int()
    (["SCENE", "--down", "2"], []),  # an abbreviation the parser takes: the loading reads the images
    (["SCENE", "--dev", "cuda"], [("SCENE", 1)]),
    (["SCENE", "--resume"], []),
    (["--steps", "3", "SCENE"], []),
    ([], []),
])
def test_which_train_commands_start_a_prefetch(monkeypatch, args, expected):
    started = []
    monkeypatch.setattr(prefetch, "start_prefetch", lambda scene, downscale: started.append((scene, downscale)))
    prefetch_scene_images(args)
    assert started == expected


@pytest.mark.parametrize("argv, local_rank, expected", [
    (["train", "s"], None, 0),
    (["train", "s", "--device", "cuda:3"], None, 3),
    (["demo", "--device=cuda"], "1", 1),
    (["fit-many", "m", "--device", "auto"], "2", 2),
    (["render", "r", "--device", "cpu"], None, None),
    (["eval", "r", "--device", "cuda:x"], None, None),
    (["eval", "r", "--device", "cuda:²"], None, None),
    (["train", "s", "--device", "cuda:3"], "1", 1),  # a rank uses cuda:LOCAL_RANK
    (["train", "s", "--device", "cpu"], "1", None),
    (["process", "photos"], None, None),
    (["bench"], None, None),
    ([], None, None),
])
def test_the_device_whose_driver_starts_early(argv, local_rank, expected):
    assert cuda_start.device_ordinal(argv, local_rank) == expected


def test_the_driver_start_ends_quietly_wherever_it_runs(monkeypatch):
    failures = []
    monkeypatch.setattr(threading, "excepthook", failures.append)
    assert cuda_start.start_cuda(["train", "s", "--device", "cpu"]) is None
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "")
    assert cuda_start.start_cuda(["train", "s"]) is None
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "0")
    thread = cuda_start.start_cuda(["train", "s", "--device", "cuda:0"])  # no driver here: nothing
    thread.join(timeout=60)
    assert not thread.is_alive() and failures == []
