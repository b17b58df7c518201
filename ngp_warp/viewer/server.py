"""``ngp-warp view RUN_OR_SCENE``: a web viewer on viser (the ``viewer`` extra).

Each browser tab sends its camera; the main thread renders it with
:func:`ngp_warp.outputs.renderer.render_view` (through :meth:`Trainer.render_image`) and sends the
frame back as the scene's background image (one ray per pixel): at a lower resolution while the camera moves, at
full resolution once it has rested for :data:`REST_SECONDS`. The training cameras are drawn as
frustums. Given a scene folder instead of a trained run, the viewer trains it live between
frames and shows the step, loss and PSNR, with pause and resume.

Camera conventions: viser's camera is ``P_world = R p_camera + t`` with OpenCV axes (+z
forward, +y down) and a vertical field of view; the trainer's cameras are OpenGL (-z forward,
+y up), so ``c2w = [R diag(1, -1, -1) | t]``.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from ngp_warp.outputs.camera_path import matrix_from_quat, quat_from_matrix
from ngp_warp.outputs.video_out import depth_video_frames

REST_SECONDS = 0.3  # the camera counts as resting this long after its last move
LIVE_REFRESH_SECONDS = 1.0  # while training live, each view is re-rendered this often
OUTPUTS = ("rgb", "depth", "opacity")
MAX_FRUSTUMS = 100
FLIP_YZ = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))


def c2w_from_viser(wxyz, position) -> torch.Tensor:
    """viser camera (wxyz [4], position [3]; OpenCV axes) → [3, 4] float32 OpenGL c2w."""
    w, x, y, z = (float(v) for v in wxyz)
    rot = matrix_from_quat(torch.tensor([x, y, z, w], dtype=torch.float64)) @ FLIP_YZ
    return torch.cat([rot, torch.tensor(position, dtype=torch.float64).reshape(3, 1)], 1).float()


def viser_from_c2w(c2w: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """[3, 4] OpenGL c2w → viser's (wxyz [4], position [3]) float64 arrays."""
    c2w = c2w.double().cpu()
    x, y, z, w = quat_from_matrix(c2w[:, :3] @ FLIP_YZ).tolist()
    return np.array([w, x, y, z]), c2w[:, 3].numpy()


def view_size(aspect: float, longest: int) -> tuple[int, int]:
    """(width, height) of a frame with ``aspect`` = width / height, ``longest`` pixels on its longer side."""
    aspect = aspect if math.isfinite(aspect) and aspect > 0 else 1.0
    if aspect >= 1:
        return longest, max(1, round(longest / aspect))
    return max(1, round(longest * aspect)), longest


def intrinsics_for(fov_y: float, width: int, height: int) -> torch.Tensor:
    """[4] float32 fx, fy, cx, cy of a centred pinhole with vertical field of view ``fov_y`` (radians)."""
    f = 0.5 * height / math.tan(0.5 * fov_y)
    return torch.tensor([f, f, width / 2, height / 2], dtype=torch.float32)


def to_image(out: dict, output: str) -> np.ndarray:
    """A render dict → [H, W, 3] uint8: rgb, depth (near bright, one scale per frame) or opacity."""
    if output == "depth":
        return depth_video_frames([out["depth"]], [out["opacity"]])[0]
    if output == "opacity":
        grey = (out["opacity"].clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu()
        return grey[..., None].expand(*grey.shape, 3).numpy()
    return (out["rgb"].clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()


@dataclass
class ClientView:
    """What one browser tab needs rendered: its camera's last move and what it was sent."""

    handle: object
    moved_at: float = 0.0  # monotonic time of the last camera update
    full_sent: bool = False  # the camera's current pose was sent at full resolution
    sent_at: float = 0.0
    frames: int = 0  # frames sent so far
    lock: threading.Lock = field(default_factory=threading.Lock)


class Viewer:
    """A viser server over a trainer: the frames, the GUI and, with ``live``, the training.

    Args:
        trainer: the trained (or training) :class:`~ngp_warp.training.trainer.Trainer`.
        host, port: where the server listens (127.0.0.1: reach it through SSH port forwarding).
        resolution: longest side of a resting frame in pixels; ``moving_resolution`` while moving.
        live: train between frames (pause and resume in the GUI).
    """

    def __init__(self, trainer, host: str, port: int, resolution: int, moving_resolution: int, live: bool):
        import viser

        self.trainer, self.live = trainer, live
        self.resolution, self.moving_resolution = resolution, moving_resolution
        self.clients: dict[int, ClientView] = {}
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.stats = {"step": trainer.step_count, "loss": float("nan"), "psnr": float("nan")}
        self.frustums = []  # viser handles of the training cameras shown
        self._add_gui()
        self._add_cameras()
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(lambda client: self.clients.pop(client.client_id, None))

    @property
    def url(self) -> str:
        host = self.server.get_host()
        return f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{self.server.get_port()}"

    def _add_gui(self) -> None:
        gui = self.server.gui
        self.output = gui.add_dropdown("Output", OUTPUTS, initial_value="rgb")
        self.still = gui.add_slider("Resolution", min=32, max=max(2048, self.resolution), step=16,
                                    initial_value=self.resolution)
        self.output.on_update(lambda _: self._redraw())
        self.still.on_update(lambda _: self._redraw())
        self.paused = gui.add_checkbox("Pause training", initial_value=False, visible=self.live)
        self.paused.on_update(lambda _: setattr(self.status, "content", self._status_text()))
        self.status = gui.add_markdown(self._status_text())

    def _add_cameras(self) -> None:
        split = self.trainer.scene.train
        c2w = self.trainer.training_c2w().cpu()  # a run with camera refinement shows its refined poses
        extent = float((c2w[:, :, 3] - c2w[:, :, 3].mean(0)).norm(dim=-1).median())
        every = max(1, math.ceil(len(split) / MAX_FRUSTUMS))
        for i in range(0, len(split), every):
            wxyz, position = viser_from_c2w(c2w[i])
            fov = 2 * math.atan(0.5 * split.height / float(split.intrinsics[i, 1]))
            self.frustums.append(self.server.scene.add_camera_frustum(
                f"/train/{i}", fov=fov, aspect=split.width / split.height, scale=0.03 * max(extent, 1e-3),
                wxyz=wxyz, position=position, color=(40, 110, 220)))
        up = c2w[:, :3, 1].mean(0)
        up = up / up.norm().clamp_min(1e-9)
        self.server.scene.set_up_direction(tuple(up.tolist()))
        centre = (self.trainer.scene.aabb[:3] + self.trainer.scene.aabb[3:]) / 2
        # behind and above the first training camera, its frustum out of the middle of the view
        offset = c2w[0, :, 3] - centre
        self.server.initial_camera.position = tuple((centre + 1.3 * offset + 0.3 * offset.norm() * up).tolist())
        self.server.initial_camera.look_at = tuple(centre.tolist())
        self.server.initial_camera.fov = 2 * math.atan(0.5 * split.height / float(split.intrinsics[0, 1]))

    def _connect(self, client) -> None:
        view = self.clients[client.client_id] = ClientView(client, moved_at=time.monotonic())

        @client.camera.on_update
        def _(_camera) -> None:
            with view.lock:
                view.moved_at, view.full_sent = time.monotonic(), False

    def _redraw(self) -> None:
        for view in list(self.clients.values()):
            view.full_sent = False

    def _status_text(self) -> str:
        s = self.stats
        if not self.live:
            return f"**trained** · step {s['step']}"
        mode = "paused" if self.paused.value else "training"
        return f"**{mode}** · step {s['step']} · loss {s['loss']:.4f} · PSNR {s['psnr']:.2f} dB"

    def render(self, view: ClientView, longest: int) -> None:
        """Render ``view``'s camera with ``longest`` pixels on the frame's longer side and send it."""
        camera = view.handle.camera
        try:
            wxyz, position, fov, aspect = camera.wxyz, camera.position, camera.fov, camera.aspect
        except (AssertionError, ZeroDivisionError):  # no camera message from this tab yet
            return
        width, height = view_size(aspect, longest)
        out = self.trainer.render_image(c2w_from_viser(wxyz, position), intrinsics_for(fov, width, height),
                                        width, height, background=self.trainer.view_background,
                                        supersample=1)
        view.handle.scene.set_background_image(to_image(out, self.output.value), format="jpeg", jpeg_quality=85)
        view.sent_at, view.frames = time.monotonic(), view.frames + 1

    def tick(self) -> bool:
        """One round: a training step (live, not paused), then every view that needs a frame.
        Returns whether anything was done."""
        busy = self.live and not self.paused.value and self._train_step()
        now = time.monotonic()
        for view in list(self.clients.values()):
            with view.lock:
                moving, full_sent, moved_at = now - view.moved_at < REST_SECONDS, view.full_sent, view.moved_at
            stale = busy and now - view.sent_at > LIVE_REFRESH_SECONDS
            if moving and view.sent_at < moved_at:
                self.render(view, min(self.moving_resolution, self.still.value))
                busy = True
            elif not moving and (not full_sent or stale):
                self.render(view, int(self.still.value))
                with view.lock:
                    view.full_sent = view.moved_at == moved_at
                busy = True
        return busy

    def _train_step(self) -> bool:
        steps, seconds = self.trainer.config.budget()
        t = self.trainer
        if (steps is not None and t.step_count >= steps) or (seconds is not None and t.train_seconds >= seconds):
            return False
        progress = max(t.step_count / steps if steps else 0.0, t.train_seconds / seconds if seconds else 0.0)
        stats = t.step(progress)
        if t.step_count % 10 == 0:  # a readout, kept in the trainer's curve as train's are
            loss = float(stats["loss"])
            psnr = t.record_readout(t.step_count, t.train_seconds, loss, float(stats["mse"]), int(stats["rays"]),
                                    int(stats["samples"]))
            self.stats = {"step": t.step_count, "loss": loss, "psnr": psnr}
            self.status.content = self._status_text()
        return True

    def serve(self, stop: threading.Event | None = None) -> None:
        """Run :meth:`tick` until ``stop`` is set (or forever), idling briefly when there is nothing to do."""
        stop = stop or threading.Event()
        while not stop.is_set():
            if not self.tick():
                stop.wait(0.02)

    def close(self) -> None:
        self.server.stop()
