"""Headless Chromium driven over the Chrome DevTools protocol (websockets, which viser brings):
the viewer's browser test and the README's screenshots (benchmarks/see_it_images.py)."""

import base64
import json
import socket
import subprocess
import time
import urllib.request
from pathlib import Path

import imageio.v3 as iio
import numpy as np

CHROMIUM = Path("/usr/bin/chromium")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class DevTools:
    """One page of a headless Chromium, driven through the Chrome DevTools protocol."""

    def __init__(self, url: str, profile: Path, width: int = 960, height: int = 640):
        from websockets.sync.client import connect

        port = free_port()
        self.process = subprocess.Popen(
            [str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             f"--user-data-dir={profile}", f"--remote-debugging-port={port}", f"--window-size={width},{height}", url],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 30
        while True:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=2) as reply:
                    pages = [t for t in json.load(reply) if t["type"] == "page"]
                if pages:
                    break
            except OSError:
                pass
            if time.monotonic() > deadline:
                raise TimeoutError("Chromium's DevTools did not come up")
            time.sleep(0.2)
        self.socket = connect(pages[0]["webSocketDebuggerUrl"], max_size=None, open_timeout=10)
        self.next_id = 0

    def call(self, method: str, **params) -> dict:
        self.next_id += 1
        self.socket.send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        while True:
            reply = json.loads(self.socket.recv(timeout=30))
            if reply.get("id") == self.next_id:
                return reply["result"]

    def screenshot(self) -> np.ndarray:
        """The page as [H, W, 3] float32 pixels."""
        png = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        return iio.imread(png)[..., :3].astype(np.float32)

    def close(self) -> None:
        self.socket.close()
        self.process.terminate()
        self.process.wait(10)


def wait_for(condition, what: str, seconds: float = 60.0) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError(f"waited {seconds} s for {what}")
        time.sleep(0.1)
