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
    that catches every exception cannot swallow it) and acted on once they have. Any other
    importer keeps Python's own Ctrl-C."""
    if _os.path.basename(_sys.argv[0]) not in ("ngp-warp", "ngp-warp.exe"):
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
        print("ngp-warp: interrupted", file=_sys.stderr)
        raise SystemExit(130)


with _interrupt_while_loading():
    from ngp_warp import _wp

    _wp.init()
    # Bound eagerly: the function ``composite`` shares its name with its module, and an eager
    # from-import keeps the package attribute pointing at the function.
    from ngp_warp.ops.composite import composite
    from ngp_warp.ops.hashgrid import HashGridEncoding
    from ngp_warp.ops.field import NGPField
    from ngp_warp.ops.occupancy import OccupancyGrid
    from ngp_warp.ops.prune import prune_samples
    from ngp_warp.ops.raymarch import MarchOptions, ray_marching
    from ngp_warp.ops.render import render_rays

__all__ = ["HashGridEncoding", "MarchOptions", "NGPField", "OccupancyGrid", "composite", "prune_samples", "ray_marching", "render_rays", "__version__"]
