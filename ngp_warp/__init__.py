"""ngp-warp: instant-NGP radiance fields whose hot paths are hand-written NVIDIA Warp kernels.

Public API (``import ngp_warp`` works without a GPU; kernels compile on first use):

* :class:`HashGridEncoding` -- multiresolution hash-grid encoding (tiny-cuda-nn semantics)
* :class:`OccupancyGrid`, :class:`MarchOptions`, :func:`ray_marching`, :func:`prune_samples`,
  :func:`composite`, :func:`render_rays`
  -- the differentiable render op
* :class:`NGPField` -- hash grid + tiny MLPs
"""

import os as _os
import sys as _sys
from contextlib import contextmanager as _contextmanager

from ngp_warp import wall_clock  # noqa: F401  (first: start-up is timed from here)

__version__ = "0.1.0"


@_contextmanager
def _interrupt_while_loading():
    """Ctrl-C while the ``ngp-warp`` command's modules load ends it as a Ctrl-C later does: one
    line and exit code 130, no traceback. The press is only noted while they load (an import
    that catches every exception cannot swallow it) and acted on once they have; of several ranks
    (``python -m ngp_warp.cli``, as ``--gpus`` and torchrun run them) the first of each machine
    prints the line (:func:`ngp_warp.training.rank_env.reports`), as the CLI's other errors.
    Any other importer, or thread, keeps Python's own Ctrl-C."""
    import threading

    command = (_os.path.basename(_sys.argv[0]) in ("ngp-warp", "ngp-warp.exe")
               or _sys.argv[0].endswith(_os.path.join("ngp_warp", "cli", "__main__.py")))  # a rank's
    if not command or threading.current_thread() is not threading.main_thread():
        yield
        return
    import signal

    pressed = []
    previous = signal.signal(signal.SIGINT, lambda *_: pressed.append(True))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if pressed:
        from ngp_warp.training import rank_env  # no torch

        if rank_env.reports():
            print("ngp-warp: interrupted", file=_sys.stderr)
        raise SystemExit(130)


# The public API loads on first use (PEP 562), so that ``import ngp_warp`` and the command
# line's argument handling stay free of torch and Warp: ``ngp-warp train --gpus N`` starts its
# ranks before anything heavy loads. Warp initialises quietly when ``ngp_warp._wp`` loads.
_PUBLIC = {"composite": "ngp_warp.ops.composite", "HashGridEncoding": "ngp_warp.ops.hashgrid",
           "NGPField": "ngp_warp.ops.field", "OccupancyGrid": "ngp_warp.ops.occupancy",
           "prune_samples": "ngp_warp.ops.prune", "MarchOptions": "ngp_warp.ops.raymarch",
           "ray_marching": "ngp_warp.ops.raymarch", "render_rays": "ngp_warp.ops.render"}

__all__ = [*sorted(_PUBLIC), "__version__"]


def __getattr__(name: str):
    if name not in _PUBLIC:
        raise AttributeError(f"module 'ngp_warp' has no attribute {name!r}")
    import importlib

    with _interrupt_while_loading():
        value = getattr(importlib.import_module(_PUBLIC[name]), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))
