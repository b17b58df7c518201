"""Pure-torch twin of the hash-grid encoding (``ngp_warp/ops/hashgrid.py``, ``kernels/hashgrid.py``),
float64 by default.

Same semantics as tiny-cuda-nn's ``HashGrid``: the cell and the fraction within it come from
the float32 position ``fmaf(scale, x, 0.5)`` exactly as the kernels (and tcnn) compute them;
weights and blending are then computed in ``dtype``. Differentiable through
torch autograd with respect to ``x`` and ``params`` (pass float64 leaves for float64
gradients). uint32 arithmetic is emulated on int64 (products split so they never overflow).
"""

from __future__ import annotations

import torch

_M32 = 0xFFFFFFFF
_PRIMES = (1, 2654435761, 805459861)


def _mul32(a: torch.Tensor, b: int) -> torch.Tensor:
    """``(a * b) mod 2^32`` for int64 ``a`` in ``[0, 2^32)`` and ``b`` in ``[0, 2^32)``."""
    lo, hi = b & 0xFFFF, b >> 16
    return (a * lo + (((a * hi) & 0xFFFF) << 16)) & _M32


def encode(
    x: torch.Tensor,
    params: torch.Tensor,
    *,
    n_features: int,
    scales,
    resolutions,
    offsets,
    hashed,
    interpolation: str = "linear",
    dtype: torch.dtype = torch.float64,
    exact: bool = False,
) -> torch.Tensor:
    """Encode ``x`` ``[N, D]`` with the flat table ``params``: ``[N, L*F]`` in ``dtype``.

    ``scales``, ``resolutions``, ``offsets`` (``L + 1`` entries) and ``hashed`` are the level
    constants of ``ngp_warp.ops.hashgrid.level_table``. ``x`` values must be float32-representable
    (the cell is chosen from their float32 value, and the fraction rounded as the kernel's);
    ``exact`` computes cell and fraction from ``x`` in ``dtype`` instead, so that the encoding is
    a smooth function of ``x`` within a cell (for ``gradcheck``).
    """
    n, D = x.shape
    F = n_features
    table = params.to(dtype).reshape(-1, F)
    x32 = x.detach().to(torch.float32).to(torch.float64)
    xs = x.to(dtype)
    outs = []
    for level, scale in enumerate(scales):
        res, off, size = resolutions[level], offsets[level], offsets[level + 1] - offsets[level]
        # fmaf(scale, x, 0.5): the float64 product of two float32 values is exact
        pos32 = (x32 * scale + 0.5).to(torch.float32).to(torch.float64)
        cell = torch.floor(pos32)
        # tcnn's float32 fraction (coarse on fine levels: pos ~ 2^19 keeps 5 fractional bits),
        # with d frac / dx = scale for autograd
        frac32 = (pos32 - cell).to(torch.float32).to(dtype)
        frac = frac32 + (xs * scale - (xs * scale).detach())
        if exact:
            cell = torch.floor(xs.detach() * scale + 0.5)
            frac = xs * scale + 0.5 - cell
        grid = cell.to(torch.int64) & _M32  # (uint32)(int)floor(pos)
        w1 = frac * frac * (3.0 - 2.0 * frac) if interpolation == "smoothstep" else frac
        w0 = 1.0 - w1
        level_table = table[off : off + size]
        acc = torch.zeros(n, F, dtype=dtype, device=x.device)
        for c in range(1 << D):
            weight = torch.ones(n, dtype=dtype, device=x.device)
            index = torch.zeros(n, dtype=torch.int64, device=x.device)
            stride = 1
            for d in range(D):
                bit = (c >> d) & 1
                coord = (grid[:, d] + bit) & _M32
                weight = weight * (w1[:, d] if bit else w0[:, d])
                if hashed[level]:
                    index = index ^ _mul32(coord, _PRIMES[d])
                else:
                    index = (index + _mul32(coord, stride)) & _M32
                    stride = (stride * res) & _M32
            index = index % size
            acc = acc + weight[:, None] * level_table[index]
        outs.append(acc)
    return torch.cat(outs, dim=1) if outs else torch.zeros(n, 0, dtype=dtype, device=x.device)


def encode_like(enc, x: torch.Tensor, params: torch.Tensor | None = None, dtype: torch.dtype = torch.float64,
                exact: bool = False):
    """:func:`encode` with the hyper-parameters of a ``HashGridEncoding`` ``enc``."""
    return encode(
        x,
        enc.params if params is None else params,
        n_features=enc.n_features_per_level,
        scales=enc.scales,
        resolutions=enc.resolutions,
        offsets=enc.offsets,
        hashed=enc.hashed,
        interpolation=enc.interpolation,
        dtype=dtype,
        exact=exact,
    )
