"""ngp-warp: instant-NGP radiance fields whose hot paths are hand-written NVIDIA Warp kernels.

Public API (``import ngp_warp`` works without a GPU; kernels compile on first use):

* :class:`HashGridEncoding` -- multiresolution hash-grid encoding (tiny-cuda-nn semantics)
* :class:`OccupancyGrid`, :class:`MarchOptions`, :func:`ray_marching`, :func:`prune_samples`,
  :func:`composite`, :func:`render_rays`
  -- the differentiable render op
* :class:`NGPField` -- hash grid + tiny MLPs
"""

from ngp_warp import wall_clock  # noqa: F401  (first: start-up is timed from here)
from ngp_warp import _wp

__version__ = "0.1.0"

_wp.init()

# Bound eagerly: the function ``composite`` shares its name with its module, and an eager
# from-import keeps the package attribute pointing at the function.
from ngp_warp.ops.composite import composite  # noqa: E402
from ngp_warp.ops.hashgrid import HashGridEncoding  # noqa: E402
from ngp_warp.ops.field import NGPField  # noqa: E402
from ngp_warp.ops.occupancy import OccupancyGrid  # noqa: E402
from ngp_warp.ops.prune import prune_samples  # noqa: E402
from ngp_warp.ops.raymarch import MarchOptions, ray_marching  # noqa: E402
from ngp_warp.ops.render import render_rays  # noqa: E402

__all__ = ["HashGridEncoding", "MarchOptions", "NGPField", "OccupancyGrid", "composite", "prune_samples", "ray_marching", "render_rays", "__version__"]
