"""ngp-warp: instant-NGP radiance fields whose hot paths are hand-written NVIDIA Warp kernels.

Public API (imported lazily, so ``import ngp_warp`` stays light and works without a GPU):

* :class:`HashGridEncoding` -- multiresolution hash-grid encoding (tiny-cuda-nn semantics)
* :class:`OccupancyGrid`, :func:`ray_marching`, :func:`composite`, :func:`render_rays`
  -- the differentiable render op
* :class:`NGPField` -- hash grid + tiny MLPs
"""

from importlib import import_module

from ngp_warp import _wp

__version__ = "0.1.0"

_wp.init()

_EXPORTS = {
    "HashGridEncoding": "ngp_warp.encoding",
    "OccupancyGrid": "ngp_warp.occupancy",
    "ray_marching": "ngp_warp.raymarch",
    "composite": "ngp_warp.composite",
    "render_rays": "ngp_warp.render",
    "NGPField": "ngp_warp.field",
}

__all__ = sorted(_EXPORTS) + ["__version__"]


def __getattr__(name):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'ngp_warp' has no attribute {name!r}")
    value = getattr(import_module(module), name)
    globals()[name] = value
    return value
