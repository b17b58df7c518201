"""Float64 pure-torch twin of ``kernels/contraction.py`` (scene contraction, its inverse, the step).

The step's Jacobian-vector product comes from autograd (``torch.func.jvp``) of the twin's own
contraction, not from the kernel's closed form, so the two are independent."""

from __future__ import annotations

import torch

from ngp_warp.kernels import contraction as K

_ORD = {"l2": 2, "linf": float("inf")}


def _box(aabb: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """(centre [3], half extents [3]) float64 of the inner box; [-1, 1]^3 when None."""
    if aabb is None:
        return torch.zeros(3, dtype=torch.float64), torch.ones(3, dtype=torch.float64)
    a = aabb.double().cpu()
    return 0.5 * (a[:3] + a[3:]), 0.5 * (a[3:] - a[:3])


def contract_normalized(x: torch.Tensor, kind: str) -> torch.Tensor:
    """[N, 3] float64 normalised points -> C(x)."""
    m = torch.linalg.vector_norm(x, ord=_ORD[kind], dim=-1, keepdim=True)
    far = (2 - 1 / m.clamp_min(1)) * x / m.clamp_min(1)
    return torch.where(m <= 1, x, far)


def contract(p: torch.Tensor, kind: str = "l2", aabb: torch.Tensor | None = None) -> torch.Tensor:
    """[N, 3] world points -> [N, 3] float64 contracted points."""
    c, h = _box(aabb)
    return contract_normalized((p.double().cpu() - c) / h, kind)


def uncontract(y: torch.Tensor, kind: str = "l2", aabb: torch.Tensor | None = None) -> torch.Tensor:
    """[N, 3] contracted points -> [N, 3] float64 world points (‖y‖ clamped to MAX_CONTRACTED)."""
    c, h = _box(aabb)
    y = y.double().cpu()
    n = torch.linalg.vector_norm(y, ord=_ORD[kind], dim=-1, keepdim=True)
    far = y / (n * (2 - n.clamp(1, K.MAX_CONTRACTED)))
    return c + h * torch.where(n <= 1, y, far)


def world_step_length(p: torch.Tensor, d: torch.Tensor, contracted_step: float, kind: str = "l2",
                      aabb: torch.Tensor | None = None) -> torch.Tensor:
    """[N, 3] world points and directions -> [N] float64 Δy / ‖J_C(x) (d / h)‖."""
    c, h = _box(aabb)
    x = (p.double().cpu() - c) / h
    v = d.double().cpu() / h
    _, jv = torch.func.jvp(lambda z: contract_normalized(z, kind), (x,), (v,))
    return contracted_step / jv.norm(dim=-1)
