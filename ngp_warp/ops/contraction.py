"""Scene contraction for unbounded scenes (mip-NeRF 360's L2 one and nerfstudio's L∞ one).

The world is normalised by an inner box (``aabb``; default: the box [-1, 1]^3, i.e. the points
are already normalised), x = (p − c) / h, and contracted radially into the ball (``"l2"``) or
cube (``"linf"``) of radius 2: C(x) = x for ‖x‖ ≤ 1, (2 − 1/‖x‖) x / ‖x‖ beyond. nerfacc's
``UN_BOUNDED_SPHERE`` is the same map followed by y / 4 + 1/2 (into [0, 1]^3); here the output
stays in [-2, 2]^3, so a field whose box is [-2, 2]^3 takes it as it is. The equations and the
Jacobian are in ``ngp_warp/kernels/contraction.py``.

How a march uses it: rays are marched in world space (t, intervals, compositing and depth stay
world quantities: σ is a density per world length), with a step of :func:`world_step_length`
for a chosen contracted spacing Δy (a constant step inside the inner region; far away it grows
between ‖x‖/2 (across the radius) and ‖x‖² (along it) times Δy); the field and the occupancy
grid are evaluated at :func:`contract` of the samples.

Forward only: these ops have no backward (positions come from the march and need no gradient);
an input that requires a gradient under autograd is refused rather than silently detached.
"""

from __future__ import annotations

import math

import torch

from ngp_warp import _wp
from ngp_warp._checks import check_aabb_values
from ngp_warp.kernels import contraction as K

__all__ = ["KINDS", "contract", "uncontract", "world_step_length"]

KINDS = {"l2": K.L2, "linf": K.LINF}


def _flag(kind) -> int:
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {sorted(KINDS)}, got {kind!r}")
    return KINDS[kind]


def _check_points(name: str, t, device=None) -> None:
    if not isinstance(t, torch.Tensor) or t.dim() != 2 or t.shape[1] != 3:
        raise ValueError(f"{name} must be a [N, 3] tensor, got {getattr(t, 'shape', type(t).__name__)}")
    if t.dtype != torch.float32:
        raise ValueError(f"{name} must be float32, got {t.dtype}")
    if device is not None and t.device != device:
        raise ValueError(f"{name} is on {t.device}, expected {device}")
    if t.requires_grad and torch.is_grad_enabled():
        raise ValueError(f"{name} requires grad, but contraction has no backward; pass {name}.detach()")
    _wp.device_of(t)


def _inner_box(aabb, device: torch.device, check_values: bool = True) -> torch.Tensor:
    """[6] float32 inner box on ``device``; [-1, 1]^3 when None. ``check_values`` reads the box
    (a host synchronisation on a GPU, not allowed inside CUDA-graph capture)."""
    if aabb is None:
        return torch.tensor([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0], device=device)
    if not isinstance(aabb, torch.Tensor) or tuple(aabb.shape) != (6,) or aabb.dtype != torch.float32:
        raise ValueError(f"aabb must be a [6] float32 tensor, got {getattr(aabb, 'shape', type(aabb).__name__)}")
    if aabb.device != device:
        raise ValueError(f"aabb is on {aabb.device}, the points on {device}")
    if check_values:
        check_aabb_values(aabb)
    return aabb.contiguous()


def contract(x: torch.Tensor, kind: str = "l2", aabb: torch.Tensor | None = None, *,
             check_box: bool = True) -> torch.Tensor:
    """Contract world points into the radius-2 ball (``"l2"``) or cube (``"linf"``).

    Args:
        x: [N, 3] float32 world points, on the CPU or a CUDA device.
        kind: ``"l2"`` (mip-NeRF 360) or ``"linf"`` (nerfstudio's L∞ contraction).
        aabb: [6] float32 inner box xmin, ymin, zmin, xmax, ymax, zmax (same device as ``x``);
            None for [-1, 1]^3. Its centre and half extents normalise x before contracting.
        check_box: check that ``aabb`` is finite with max > min (one host synchronisation on a
            GPU); callers whose box was checked once already (the field, the occupancy grid)
            pass False, which also lets the call be captured in a CUDA graph.

    Returns:
        [N, 3] float32 contracted points y with ‖y‖ < 2 (‖y‖ ≤ 1 exactly for the inner region);
        no gradient.
    """
    _check_points("x", x)
    flag, box = _flag(kind), _inner_box(aabb, x.device, check_box)
    out = torch.empty(x.shape, dtype=x.dtype, device=x.device)  # contiguous whatever x's strides
    _wp.launch(K.contract_points, x.shape[0], [x.contiguous(), box, flag, out], _wp.device_of(x))
    return out


def uncontract(y: torch.Tensor, kind: str = "l2", aabb: torch.Tensor | None = None, *,
               check_box: bool = True) -> torch.Tensor:
    """Inverse of :func:`contract`: contracted points back to world points.

    Args:
        y: [N, 3] float32 contracted points; ‖y‖ is clamped to 2 − 2^-20, so a point on or
            beyond the radius-2 boundary comes back at normalised distance 2^20 (about 1e6),
            along its own direction.
        kind, aabb, check_box: as for :func:`contract`.

    Returns:
        [N, 3] float32 world points; no gradient.
    """
    _check_points("y", y)
    flag, box = _flag(kind), _inner_box(aabb, y.device, check_box)
    out = torch.empty(y.shape, dtype=y.dtype, device=y.device)  # contiguous whatever y's strides
    _wp.launch(K.uncontract_points, y.shape[0], [y.contiguous(), box, flag, out], _wp.device_of(y))
    return out


def world_step_length(x: torch.Tensor, directions: torch.Tensor, contracted_step: float, kind: str = "l2",
                      aabb: torch.Tensor | None = None) -> torch.Tensor:
    """World length of a step at ``x`` along ``directions`` that spans ``contracted_step`` once contracted.

    .. math:: \\Delta t = \\Delta y / \\|J_C(x)\\,(d \\oslash h)\\|

    (first order; J_C is the contraction's Jacobian, h the inner box's half extents). Inside the
    inner region this is Δy / ‖d ⊘ h‖; far away, normalised, it grows between ‖x‖/2 (d across
    the radius) and ‖x‖² (d along it) times Δy.

    Args:
        x: [N, 3] float32 world points. directions: [N, 3] float32 non-zero ray directions
            (same device; unit length when Δt is to be a distance).
        contracted_step: Δy > 0, the spacing wanted in contracted space.
        kind, aabb: as for :func:`contract`.

    Returns:
        [N] float32 world step lengths Δt (in units of t along the given directions).
    """
    _check_points("x", x)
    _check_points("directions", directions, x.device)
    if directions.shape[0] != x.shape[0]:
        raise ValueError(f"directions has {directions.shape[0]} rows, x has {x.shape[0]}")
    if (isinstance(contracted_step, bool) or not isinstance(contracted_step, (int, float))
            or not 0 < contracted_step < math.inf):
        raise ValueError(f"contracted_step must be a positive finite number, got {contracted_step!r}")
    flag, box = _flag(kind), _inner_box(aabb, x.device)
    out = torch.empty(x.shape[0], dtype=torch.float32, device=x.device)
    _wp.launch(K.world_step_lengths, x.shape[0],
               [x.contiguous(), directions.contiguous(), box, flag, float(contracted_step), out], _wp.device_of(x))
    return out
