"""The viser viewer: camera conventions, live training with pause, and a real browser (headless
Chromium driven over the DevTools protocol) that shows the scene and follows the camera."""

import math
import shutil
import socket
import threading
import time
from argparse import Namespace

import numpy as np
import pytest
import torch

from browser import CHROMIUM, DevTools, wait_for
from ngp_warp.outputs.camera_path import matrix_from_quat
from ngp_warp.training.checkpoint import load_trainer, save_checkpoint
from ngp_warp.cli import main
from ngp_warp.training.config import TrainConfig
from ngp_warp.data.loading import load_scene
from ngp_warp.ops.field import FieldConfig
from ngp_warp.data.scene import write_demo_scene
from ngp_warp.training.trainer import Trainer

viser = pytest.importorskip("viser")
from ngp_warp.cli.view import load_target  # noqa: E402
from ngp_warp.viewer.server import Viewer, c2w_from_viser, to_image, view_size, viser_from_c2w  # noqa: E402


def tiny_config(steps: int) -> TrainConfig:
    return TrainConfig(steps=steps, target_samples=1 << 12, grid_resolution=32, steps_per_diagonal=256,
                       field=FieldConfig(n_levels=8, log2_hashmap_size=14, finest_resolution=128.0, hidden=32))


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    return write_demo_scene(tmp_path_factory.mktemp("viewer") / "scene", width=32, height=32, n_train=16,
                            n_test=1, supersample=1)


def test_cameras_round_trip_through_viser_conventions():
    q = torch.nn.functional.normalize(torch.tensor([0.3, -0.5, 0.2, 0.8], dtype=torch.float64), dim=0)
    c2w = torch.cat([matrix_from_quat(q), torch.tensor([[1.0], [-2.0], [0.5]], dtype=torch.float64)], 1).float()
    wxyz, position = viser_from_c2w(c2w)
    torch.testing.assert_close(c2w_from_viser(wxyz, position), c2w, rtol=0, atol=1e-6)
    w, x, y, z = wxyz  # viser's camera looks down its +z, the OpenGL camera down its -z
    forward = matrix_from_quat(torch.tensor([x, y, z, w]))[:, 2]
    torch.testing.assert_close(forward.float(), -c2w[:, 2], rtol=0, atol=1e-6)


def test_frame_sizes_and_images():
    assert view_size(2.0, 100) == (100, 50) and view_size(0.5, 100) == (50, 100) and view_size(0.0, 64) == (64, 64)
    depth, opacity = torch.tensor([[1.0, 2.0], [4.0, 0.0]]), torch.tensor([[1.0, 1.0], [1.0, 0.0]])
    out = {"rgb": torch.rand(2, 2, 3), "depth": depth, "opacity": opacity}
    rgb, grey, alpha = (to_image(out, k) for k in ("rgb", "depth", "opacity"))
    assert rgb.shape == grey.shape == alpha.shape == (2, 2, 3) and rgb.dtype == np.uint8
    assert grey[0, 0, 0] > grey[0, 1, 0] > grey[1, 0, 0] and grey[1, 1, 0] == 0  # near bright, empty black
    assert alpha[0, 0, 0] == 255 and alpha[1, 1, 0] == 0


def test_live_training_steps_until_paused(scene_dir):
    trainer = Trainer(load_scene(scene_dir), tiny_config(1000), device="cpu")
    viewer = Viewer(trainer, "127.0.0.1", 0, resolution=32, moving_resolution=16, live=True)
    try:
        for _ in range(12):
            assert viewer.tick()
        assert trainer.step_count == 12 and viewer.stats["step"] == 10
        assert "training" in viewer.status.content and "step 10" in viewer.status.content
        viewer.paused.value = True
        assert not viewer.tick() and trainer.step_count == 12  # no client, nothing to render
    finally:
        viewer.close()


def test_a_refined_run_shows_its_refined_cameras(scene_dir):
    trainer = Trainer(load_scene(scene_dir), TrainConfig(**{**vars(tiny_config(1)), "camera_refinement": True}),
                      device="cpu")
    with torch.no_grad():
        trainer.cameras.omega[0] = torch.tensor([0.1, -0.05, 0.02])
        trainer.cameras.tau[0] = torch.tensor([0.02, 0.0, -0.03])
    viewer = Viewer(trainer, "127.0.0.1", 0, resolution=32, moving_resolution=16, live=False)
    try:
        wxyz, position = viser_from_c2w(trainer.cameras.refined_c2w(trainer.scene.train.c2w)[0])
        np.testing.assert_allclose(viewer.frustums[0].wxyz, wxyz, atol=1e-6)
        np.testing.assert_allclose(viewer.frustums[0].position, position, atol=1e-6)
        original = viser_from_c2w(trainer.scene.train.c2w[0])
        assert np.abs(viewer.frustums[0].position - original[1]).max() > 0.02
        assert not np.allclose(viewer.frustums[0].wxyz, original[0], atol=1e-2)
        np.testing.assert_allclose(viewer.frustums[1].wxyz, viser_from_c2w(trainer.scene.train.c2w[1])[0], atol=1e-6)
    finally:
        viewer.close()


def test_a_scene_folder_is_trained_live(scene_dir):
    args = Namespace(target=str(scene_dir), scene=None, steps=7, seconds=None, seed=0, target_samples=4096,
                     set=["grid_resolution=32"], downscale=2)
    trainer, live = load_target(args, "cpu")
    assert live and trainer.step_count == 0 and trainer.config.budget() == (7, None)
    assert trainer.scene.train.width == 16 and trainer.config.grid_resolution == 32
    assert trainer.config.field.log2_hashmap_size == 16  # the CPU's table (config.cpu_sizes)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def stopped_after(ticks: int, stop: type[BaseException] = KeyboardInterrupt):
    """A Viewer.serve that ticks ``ticks`` times, then stops as Ctrl-C does (or raises ``stop``)."""
    def serve(viewer, event=None):
        for _ in range(ticks):
            viewer.tick()
        raise stop
    return serve


LIVE = ["--device", "cpu", "--target-samples", "4096", "--set", "grid_resolution=32", "--steps", "100"]


def test_a_live_run_is_kept_in_out_when_the_viewer_stops(scene_dir, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(Viewer, "serve", stopped_after(25))
    out = tmp_path / "live"
    assert main(["view", str(scene_dir), "--port", str(free_port()), "--out", str(out), *LIVE]) == 130
    err = capsys.readouterr().err
    assert f"saved at step 25 to {out}" in err and "not kept" not in err
    trainer, record = load_trainer(out / "checkpoint.pt", device="cpu")
    assert trainer.step_count == 25 and record["downscale"] == 1 and (out / "normalisation.json").is_file()
    rows = (out / "training_curve.csv").read_text().splitlines()[1:]
    assert [int(float(r.split(",")[0])) for r in rows] == [10, 20]  # the viewer's readouts
    # the folder now holds a run: another live run needs --overwrite, and says so before training
    assert main(["view", str(scene_dir), "--port", str(free_port()), "--out", str(out), *LIVE]) == 2
    assert "holds another run" in capsys.readouterr().err.strip().splitlines()[-1]
    monkeypatch.setattr(Viewer, "serve", stopped_after(3))
    assert main(["view", str(scene_dir), "--port", str(free_port()), "--out", str(out), "--overwrite", *LIVE]) == 130
    assert load_trainer(out / "checkpoint.pt", device="cpu")[0].step_count == 3
    # a trained run is viewed, not trained: live training's flags are refused in one line
    assert main(["view", str(out), "--port", str(free_port()), "--device", "cpu", "--out", str(tmp_path / "x"),
                 "--seed", "3"]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == \
        f"ngp-warp: error: --seed, --out: settings of live training, but {out} is a trained run " \
        f"(give a scene folder to train one live)"


def test_a_live_run_stopped_before_a_step_leaves_no_folder(scene_dir, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(Viewer, "serve", stopped_after(0))
    out = tmp_path / "never"
    assert main(["view", str(scene_dir), "--port", str(free_port()), "--out", str(out), *LIVE]) == 130
    assert f"nothing trained; nothing written to {out}" in capsys.readouterr().err and not out.exists()


def test_a_live_run_without_out_says_it_is_not_kept(scene_dir, monkeypatch, capsys):
    monkeypatch.setattr(Viewer, "serve", stopped_after(2))
    assert main(["view", str(scene_dir), "--port", str(free_port()), *LIVE]) == 130
    assert "training live, not kept: --out DIR keeps it" in capsys.readouterr().err


def test_a_failed_step_is_not_saved_over_the_folder(scene_dir, tmp_path, monkeypatch):
    monkeypatch.setattr(Viewer, "serve", stopped_after(2, RuntimeError))
    out = tmp_path / "failed"
    with pytest.raises(RuntimeError):
        main(["view", str(scene_dir), "--port", str(free_port()), "--out", str(out), *LIVE])
    assert not out.exists()


def test_out_that_cannot_take_a_live_run_is_one_line(scene_dir, tmp_path, capsys):
    port = str(free_port())
    (tmp_path / "a_file").write_text("")
    assert main(["view", str(scene_dir), "--port", port, "--out", str(tmp_path / "a_file" / "run"), *LIVE]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1].endswith("is not a writable folder)")
    assert main(["view", str(scene_dir), "--port", port, "--out", str(scene_dir / "run"), *LIVE]) == 2
    assert "would be written into the dataset" in capsys.readouterr().err.strip().splitlines()[-1]
    assert main(["view", str(scene_dir), "--port", port, "--overwrite", *LIVE]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == \
        "ngp-warp: error: --overwrite: replaces the run --out holds, but no --out is given"


def test_a_setting_that_does_not_suit_the_scene_is_one_line(scene_dir, capsys):
    assert main(["view", str(scene_dir), "--device", "cpu", "--set", "camera_refinement=true",
                 "--set", "contraction=l2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("ngp-warp: error: --set: camera_refinement needs a bounded scene"), err


def test_view_of_a_missing_folder_is_one_line(tmp_path, capsys):
    assert main(["view", str(tmp_path / "nope"), "--device", "cpu"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("ngp-warp: error: ") and "no such run or scene folder" in err[-1]


def test_a_busy_port_or_a_foreign_host_is_one_line_before_loading(tmp_path, capsys):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        missing = str(tmp_path / "nope")  # the address is checked before the run would be loaded
        assert main(["view", missing, "--device", "cpu", "--port", str(port)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1] == f"ngp-warp: error: --port {port}: already in use on 127.0.0.1 (choose another --port, " \
                          f"and forward that one)", err
    assert main(["view", missing, "--device", "cpu", "--host", "10.255.255.1"]) == 2  # not this machine's
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("ngp-warp: error: --host 10.255.255.1 --port 8080: cannot listen there"), err
    with pytest.raises(SystemExit):
        main(["view", missing, "--port", "70000"])
    assert "expected a positive int up to 65535" in capsys.readouterr().err


# ---- a real browser ------------------------------------------------------------------------------

def rested_frames(viewer: Viewer) -> int:
    """Frames sent to the one browser tab when its current camera has its full-resolution frame, else -1."""
    views = list(viewer.clients.values())
    return views[0].frames if len(views) == 1 and views[0].full_sent else -1


@pytest.mark.skipif(not CHROMIUM.exists(), reason="needs Debian's chromium (/usr/bin/chromium)")
def test_browser_shows_the_scene_and_follows_the_camera(scene_dir, tmp_path):
    trainer = Trainer(load_scene(scene_dir), tiny_config(60), device="cpu")
    trainer.train(show_progress=False)
    run = tmp_path / "run"
    run.mkdir()
    save_checkpoint(trainer, run / "checkpoint.pt", scene_dir, 1)
    loaded, live = load_target(Namespace(target=str(run), scene=None), "cpu")
    assert not live and loaded.step_count == 60
    viewer = Viewer(loaded, "127.0.0.1", 0, resolution=160, moving_resolution=40, live=False)
    stop = threading.Event()
    server = threading.Thread(target=viewer.serve, args=(stop,), daemon=True)
    server.start()
    browser = None
    try:
        browser = DevTools(viewer.url, tmp_path / "profile")
        wait_for(lambda: rested_frames(viewer) > 0, "the first full frame")
        assert browser.call("Runtime.evaluate", expression="document.readyState")["result"]["value"] == "complete"
        assert browser.call("Runtime.evaluate", expression="document.querySelectorAll('canvas').length",
                            returnByValue=True)["result"]["value"] >= 1
        time.sleep(1.5)  # the browser draws the frame
        first = browser.screenshot()
        centre = first[160:480, 160:560]  # the middle of the page: the scene, clear of the panels
        assert centre.std() > 8.0, centre.std()  # not a blank canvas

        sent = rested_frames(viewer)
        client = next(iter(viewer.clients.values())).handle
        look_at = (loaded.scene.aabb[:3] + loaded.scene.aabb[3:]) / 2
        eye = torch.tensor(client.camera.position, dtype=torch.float32) - look_at
        turn = torch.tensor([[math.cos(1.2), -math.sin(1.2), 0.0], [math.sin(1.2), math.cos(1.2), 0.0], [0, 0, 1]])
        client.camera.position = (look_at + 0.7 * turn @ eye).numpy()  # nearer, and around the up (+z) axis
        wait_for(lambda: rested_frames(viewer) > sent, "the frame of the moved camera")
        time.sleep(1.5)
        moved = browser.screenshot()[160:480, 160:560]
        assert np.abs(moved - centre).mean() > 4.0, np.abs(moved - centre).mean()
    finally:
        if browser is not None:
            browser.close()
        stop.set()
        server.join(30)
        viewer.close()
        shutil.rmtree(tmp_path / "profile", ignore_errors=True)
