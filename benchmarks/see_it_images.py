"""The "See it" pictures of docs/outputs.md, from a trained demo run, on the CPU:

* ``docs/viewer.png``: ``ngp-warp view RUN`` in headless Chromium (the first training camera);
* ``docs/mesh.png``: ``ngp-warp export RUN --mesh mesh.ply`` shown in a bare viser scene.

    ngp-warp demo --out runs/demo --device cpu
    python benchmarks/see_it_images.py runs/demo

Needs viser (the ``viewer`` extra) and Debian's chromium; the browser is driven by
``tests/browser.py``.
"""

from __future__ import annotations

import argparse
import math
import shutil
import sys
import tempfile
import threading
import time
from argparse import Namespace
from pathlib import Path

import imageio.v3 as iio
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from browser import DevTools, wait_for  # noqa: E402

from ngp_warp.cli import main as ngp_warp  # noqa: E402
from ngp_warp.outputs.ply import read_ply  # noqa: E402
from ngp_warp.cli.view import load_target  # noqa: E402
from ngp_warp.viewer.server import Viewer, viser_from_c2w  # noqa: E402

WIDTH, HEIGHT = 800, 500


def clean_screenshot(browser: DevTools) -> np.ndarray:
    """The page without the software-WebGL notice (headless Chromium has no GPU)."""
    browser.call("Runtime.evaluate", expression="document.querySelectorAll('.mantine-Notification-root')"
                                                ".forEach(n => n.remove())")
    time.sleep(0.5)
    return browser.screenshot().astype(np.uint8)


def viewer_picture(run: Path, out: Path, profile: Path) -> None:
    trainer, _ = load_target(Namespace(target=str(run), scene=None), "cpu")
    viewer = Viewer(trainer, "127.0.0.1", 0, resolution=400, moving_resolution=100, live=False)
    stop = threading.Event()
    thread = threading.Thread(target=viewer.serve, args=(stop,), daemon=True)
    thread.start()
    browser = DevTools(viewer.url, profile, WIDTH, HEIGHT)
    try:
        wait_for(lambda: any(v.full_sent and v.frames for v in viewer.clients.values()), "a full frame", 120)
        time.sleep(2.0)
        iio.imwrite(out, clean_screenshot(browser), optimize=True)
    finally:
        browser.close()
        stop.set()
        thread.join(60)
        viewer.close()


def mesh_picture(run: Path, mesh_path: Path, out: Path, profile: Path) -> None:
    import trimesh  # comes with viser
    import viser

    from ngp_warp.training.checkpoint import load_trainer
    from ngp_warp.cli import CHECKPOINT

    ply = read_ply(mesh_path)
    mesh = trimesh.Trimesh(ply["vertices"], ply["faces"], vertex_colors=ply["colors"], process=False)
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    server.scene.add_mesh_trimesh("/mesh", mesh)
    split = load_trainer(run / CHECKPOINT, device="cpu")[0].scene.train
    up = split.c2w[:, :3, 1].mean(0)
    server.scene.set_up_direction(tuple((up / up.norm()).tolist()))
    browser = DevTools(f"http://127.0.0.1:{server.get_port()}", profile, WIDTH, HEIGHT)
    try:
        wait_for(lambda: len(server.get_clients()) == 1, "the browser", 60)
        client = next(iter(server.get_clients().values()))
        wait_for(lambda: client.camera.update_timestamp > 0, "the browser's camera", 60)
        wxyz, position = viser_from_c2w(split.c2w[0])
        client.camera.wxyz, client.camera.position = wxyz, position
        client.camera.fov = 2 * math.atan(0.5 * split.height / float(split.intrinsics[0, 1]))
        time.sleep(10.0)
        iio.imwrite(out, clean_screenshot(browser), optimize=True)
    finally:
        browser.close()
        server.stop()


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="a trained demo output folder")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "docs")
    parser.add_argument("--resolution", type=int, default=192, help="marching-cubes resolution")
    args = parser.parse_args(argv)
    args.out.mkdir(exist_ok=True)
    mesh = args.run / "mesh.ply"
    assert ngp_warp(["export", str(args.run), "--mesh", "mesh.ply", "--resolution", str(args.resolution),
                     "--device", "cpu", "--quiet"]) == 0
    with tempfile.TemporaryDirectory() as tmp:
        viewer_picture(args.run, args.out / "viewer.png", Path(tmp) / "viewer")
        mesh_picture(args.run, mesh, args.out / "mesh.png", Path(tmp) / "mesh")
        shutil.rmtree(tmp, ignore_errors=True)
    for name in ("viewer.png", "mesh.png"):
        print(f"wrote {args.out / name} ({(args.out / name).stat().st_size // 1024} KB)")


if __name__ == "__main__":
    main()
