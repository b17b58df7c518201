"""Multi-cascade occupancy grid: a per-cell density estimate and an occupancy bitfield.

Cascade ``l`` covers the base box scaled by :math:`2^l` about its centre and is split into
``resolution³`` cells; a point belongs to the finest cascade that contains it. The grid is
refreshed from a density callable with instant-ngp / nerfacc semantics:

.. math::

    \\mathrm{occ}_c \\leftarrow \\max(\\mathrm{occ}_c \\cdot \\mathrm{decay},\\; \\sigma(x_c)),
    \\qquad
    \\mathrm{occupied}_c = \\mathrm{occ}_c > \\min(\\tau, \\overline{\\mathrm{occ}})

where :math:`x_c` is a uniformly jittered point in cell :math:`c` and the mean runs over visible
cells. Cells no training camera sees hold ``-1`` and are never occupied.

With a scene contraction (:mod:`ngp_warp.ops.contraction`) the grid lives in contracted space: one
cascade over the radius-2 ball's box [-2, 2]³, whose cells are looked up at C(x) by the march
and filled from densities at C⁻¹ of their points.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import nn

from ngp_warp import _wp
from ngp_warp._checks import check_aabb_values, check_distances
from ngp_warp.ops.contraction import KINDS, uncontract
from ngp_warp.kernels import occupancy as K
from ngp_warp.ops.op_registry import register

_MAX_LEVELS = 16
_MAX_MIPS = 4  # the march jumps over empty blocks of up to 16³ cells


def host_seed() -> int:
    """A kernel RNG seed from torch's default CPU generator (reproducible, never syncs a GPU)."""
    return int(torch.randint(0, 2**31 - 1, (1,)).item())


def _storage_key(t: torch.Tensor) -> tuple | None:
    """(version counter, address) of a tensor: changes with every in-place torch write (None for
    inference tensors, which keep no version counter)."""
    try:
        return t._version, t.data_ptr()
    except RuntimeError:
        return None


def _parse_aabb(aabb) -> list[float]:
    values = torch.as_tensor(aabb, dtype=torch.float64).detach().cpu().reshape(-1)
    if values.numel() != 6:
        raise ValueError(f"aabb must hold 6 values (min_xyz, max_xyz), got shape {tuple(torch.as_tensor(aabb).shape)}")
    check_aabb_values(values)
    return values.tolist()


def _camera_rows(c2w, intrinsics, width: int, height: int, dev: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """Checked cameras as the kernels take them: [N, 12] float32 c2w rows, [N, 4] intrinsics."""
    if not isinstance(c2w, torch.Tensor) or c2w.dim() not in (2, 3) or tuple(c2w.shape[-2:]) not in ((3, 4), (4, 4)):
        raise ValueError(f"c2w must be a [N, 3, 4] or [N, 4, 4] tensor, got {getattr(c2w, 'shape', c2w)}")
    c2w = c2w.reshape(-1, *c2w.shape[-2:])
    if not isinstance(intrinsics, torch.Tensor) or intrinsics.shape[-1:] != (4,) or intrinsics.dim() > 2:
        raise ValueError(f"intrinsics must be a [N, 4] tensor (fx, fy, cx, cy), got {getattr(intrinsics, 'shape', intrinsics)}")
    intrinsics = intrinsics.reshape(-1, 4).expand(c2w.shape[0], 4) if intrinsics.numel() == 4 else intrinsics
    if intrinsics.shape[0] != c2w.shape[0]:
        raise ValueError(f"c2w holds {c2w.shape[0]} cameras but intrinsics {intrinsics.shape[0]}")
    if width <= 0 or height <= 0:
        raise ValueError(f"width and height must be positive, got {width}×{height}")
    c2w_flat = c2w[:, :3, :4].to(device=dev, dtype=torch.float32).reshape(-1, 12).contiguous()
    intr = intrinsics.to(device=dev, dtype=torch.float32).contiguous()
    return c2w_flat, intr


class OccupancyGrid(nn.Module):
    """Occupancy grid over ``levels`` cascades of ``resolution³`` cells.

    Args:
        aabb: 6 floats ``(x_min, y_min, z_min, x_max, y_max, z_max)``, the finest cascade's box.
        resolution: cells per axis per cascade (a multiple of 4 when ``levels > 1``, so that
            each cascade's cells tile the next finer box exactly).
        levels: number of cascades (1 to 16).
        contraction: None, or ``"l2"`` / ``"linf"`` (see :func:`ngp_warp.ops.contraction.contract`):
            then ``aabb`` is the contraction's inner box (world) and the grid one cascade
            (``levels`` must be 1) over the contracted box [-2, 2]³.

    Buffers (follow ``.to()`` and ``state_dict``):
        aabb: [6] float32, the base box in grid coordinates ([-2, 2]³ with a contraction).
        inner_aabb: [6] float32, only with a contraction: its inner box in the world. occs: [levels·resolution³] float32 per-cell estimate, -1 = invisible.
        threshold: [1] float32, the occupancy threshold of the last update (-1 before any).
        bitfield: [ceil(levels·resolution³ / 8)] uint8, bit ``id & 7`` of byte ``id >> 3`` says
        whether cell ``id = ((level·R + i)·R + j)·R + k`` is occupied.
        mips: [levels·mip_cells] uint8 (not saved), per cascade ``n_mips`` levels of blocks of
        2^m cells per axis, zero where all cells are empty (see :mod:`ngp_warp.kernels.occupancy`);
        derived from ``bitfield`` by :meth:`march_mips`, which rebuilds them after any in-place
        change of ``bitfield``.

    A fresh grid has every cell occupied.
    """

    def __init__(self, aabb, resolution: int = 128, levels: int = 1, contraction: str | None = None):
        super().__init__()
        register(self)  # the compiled march names its grid by number
        if contraction is not None and contraction not in KINDS:
            raise ValueError(f"contraction must be None or one of {sorted(KINDS)}, got {contraction!r}")
        if contraction is not None and levels != 1:
            raise ValueError(f"a contracted grid has one cascade, got levels={levels!r}")
        if not isinstance(resolution, int) or resolution < 1:
            raise ValueError(f"resolution must be a positive int, got {resolution!r}")
        if not isinstance(levels, int) or not 1 <= levels <= _MAX_LEVELS:
            raise ValueError(f"levels must be an int in [1, {_MAX_LEVELS}], got {levels!r}")
        if levels > 1 and resolution % 4 != 0:
            raise ValueError(f"resolution must be a multiple of 4 when levels > 1, got {resolution}")
        if levels * resolution**3 >= 2**31:
            raise ValueError(f"levels · resolution³ must stay below 2^31, got {levels} · {resolution}³")
        device = aabb.device if isinstance(aabb, torch.Tensor) else None
        self.contraction = contraction
        self._inner_host = _parse_aabb(aabb) if contraction is not None else None
        self._aabb_host = _parse_aabb(aabb) if contraction is None else [-2.0] * 3 + [2.0] * 3
        self.resolution = resolution
        self.levels = levels
        n = levels * resolution**3
        self.register_buffer("aabb", torch.tensor(self._aabb_host, dtype=torch.float32, device=device))
        if contraction is not None:
            self.register_buffer("inner_aabb", torch.tensor(self._inner_host, dtype=torch.float32, device=device))
        self.register_buffer("occs", torch.zeros(n, dtype=torch.float32, device=device))
        self.register_buffer("threshold", torch.full((1,), -1.0, dtype=torch.float32, device=device))
        self.register_buffer("bitfield", torch.full(((n + 7) // 8,), 255, dtype=torch.uint8, device=device))
        self.register_buffer("_splat", torch.full((n,), -1.0, dtype=torch.float32, device=device), persistent=False)
        self.n_mips = min(_MAX_MIPS, (resolution & -resolution).bit_length() - 1)  # R % 2^n_mips = 0
        self._mip_bases = [sum((resolution >> k) ** 3 for k in range(1, m)) for m in range(1, self.n_mips + 2)]
        self.mip_cells = self._mip_bases[-1]
        self.register_buffer("mips", torch.ones(levels * self.mip_cells, dtype=torch.uint8, device=device),
                             persistent=False)
        self._mips_key = None
        # count_seen_only's cameras ([N, 12] c2w rows, [N, 4] intrinsics) and (width, height, near, margin)
        self.register_buffer("_seen_c2w", None, persistent=False)
        self.register_buffer("_seen_intrinsics", None, persistent=False)
        self._seen_frame: tuple[float, float, float, float] | None = None
        # data-parallel training: merges an update's per-cell sample maxima ([n_cells] float32,
        # -1 where none) over the ranks, in place, so that every rank's grid stays the same
        self.merge_samples: Callable[[torch.Tensor], None] | None = None
        self.register_load_state_dict_post_hook(lambda module, _keys: module._sync_host_aabb())


    def __setstate__(self, state):  # copies and unpickled grids are known to the compiled march too
        super().__setstate__(state)
        register(self)

    def _sync_host_aabb(self) -> None:
        self._aabb_host = _parse_aabb(self.aabb)
        if self.contraction is not None:
            self._inner_host = _parse_aabb(self.inner_aabb)

    @property
    def n_cells(self) -> int:
        return self.levels * self.resolution**3

    @property
    def aabb_host(self) -> list[float]:
        """The base box as 6 Python floats (no device access)."""
        return list(self._aabb_host)

    @property
    def inner_aabb_host(self) -> list[float] | None:
        """The contraction's inner box as 6 Python floats (None without a contraction)."""
        return None if self._inner_host is None else list(self._inner_host)

    @property
    def default_step_size(self) -> float:
        """instant-ngp's marching step: the base box diagonal / 1024 (√3/1024 for the unit cube;
        4√3/1024 in contracted space with a contraction)."""
        lo, hi = self._aabb_host[:3], self._aabb_host[3:]
        return math.sqrt(sum((b - a) ** 2 for a, b in zip(lo, hi))) / 1024.0

    def occupied(self) -> torch.Tensor:
        """The bitfield unpacked: bool [levels, R, R, R] (indexed level, x, y, z)."""
        shifts = torch.arange(8, device=self.bitfield.device, dtype=torch.uint8)
        bits = (self.bitfield[:, None] >> shifts) & 1
        r = self.resolution
        return bits.reshape(-1)[: self.n_cells].bool().reshape(self.levels, r, r, r)

    @torch.no_grad()
    def update(
        self,
        step: int,
        density_fn: Callable[[torch.Tensor], torch.Tensor],
        occ_threshold: float = 0.01,
        ema_decay: float = 0.95,
        warmup_steps: int = 256,
        every_n: int = 16,
        chunk: int = 1 << 18,
    ) -> bool:
        """Refresh the grid when ``step % every_n == 0``; returns whether it did.

        During warm-up (``step < warmup_steps``) every cell is evaluated at a jittered point
        inside it; afterwards ``n_cells // 4`` uniformly drawn cells plus as many drawn from the
        occupied ones (uniformly among them, by bisection of their prefix count; no host sync).
        After :meth:`count_seen_only`, a point that none of its cameras sees counts as σ = 0.
        Then ``occ ← max(occ·ema_decay, σ)`` on sampled visible cells (the max of all samples
        of a cell) and ``occupied = occ > min(occ_threshold, mean visible occ)``.

        Args:
            step: the training step.
            density_fn: world points [M, 3] float32 → densities [M] or [M, 1] (any float dtype),
                called under ``torch.no_grad()`` on chunks of at most ``chunk`` points. instant-ngp
                stores the optical thickness of one step here, i.e. ``σ(x) · step_size``.
        """
        if every_n < 1 or step % every_n != 0:
            return False
        if chunk < 1:
            raise ValueError(f"chunk must be positive, got {chunk}")
        device = _wp.device_of(self.occs)
        n = self.n_cells
        warmup = step < warmup_steps
        if warmup:
            n_uniform = n_samples = n
            prefix = None
        else:
            n_uniform = n // 4
            n_samples = 2 * n_uniform
            prefix = torch.cumsum(self.occupied().reshape(-1), 0, dtype=torch.int32)
        seed = host_seed()
        for lo in range(0, n_samples, chunk):
            m = min(chunk, n_samples - lo)
            cells, points = self._draw(lo, m, warmup, n_uniform, seed, prefix)
            if self.contraction is not None:
                points = uncontract(points, self.contraction, self.inner_aabb, check_box=False)
            values = density_fn(points)
            if not isinstance(values, torch.Tensor) or values.numel() != m or values.shape[0] != m:
                shape = tuple(values.shape) if isinstance(values, torch.Tensor) else type(values).__name__
                raise ValueError(f"density_fn must return [{m}] or [{m}, 1] densities, got {shape}")
            values = values.detach().reshape(m).to(torch.float32).contiguous()
            if self._seen_frame is not None:
                self._zero_unseen(points, values)
            # Scatter-max into arbitrary cells: one CPU thread (align=m), as CPU atomics are not atomic.
            _wp.launch(K.splat_max, m, [cells, values, self._splat], device, align=m)
        if self.merge_samples is not None:
            self.merge_samples(self._splat)
        _wp.launch(K.ema_update, n, [self._splat, float(ema_decay), self.occs], device)
        visible = self.occs >= 0
        mean = (self.occs * visible).sum() / visible.sum().clamp(min=1)
        self.threshold.copy_(torch.clamp(mean, max=occ_threshold).reshape(1))
        self._pack()
        return True

    @torch.no_grad()
    def mark_invisible_cells(self, c2w: torch.Tensor, intrinsics: torch.Tensor, width: int, height: int,
                             near_plane: float = 0.0) -> None:
        """Set cells that no camera sees to -1 (never occupied, never updated).

        A cell is visible when one of its 8 corners (with a contraction: C⁻¹ of them) projects
        inside some image (``0 ≤ u ≤ width``, ``0 ≤ v ≤ height``) in front of that camera's
        ``near_plane``.

        Args:
            c2w: [N, 3, 4] or [N, 4, 4] (or one [3, 4] / [4, 4]) float camera-to-world matrices,
                OpenGL convention (camera looks down -z, +y up).
            intrinsics: [N, 4] (or [4]) float ``fx, fy, cx, cy`` in pixels.
            width, height: image size in pixels.
        """
        c2w_flat, intr = _camera_rows(c2w, intrinsics, width, height, self.occs.device)
        _wp.launch(
            K.mark_visible, self.n_cells,
            [self.aabb, self.resolution, KINDS.get(self.contraction, -1),
             self.inner_aabb if self.contraction is not None else self.aabb, c2w_flat, intr, c2w_flat.shape[0],
             float(width), float(height), float(near_plane), self.occs],
            _wp.device_of(self.occs),
        )
        self._pack()

    @torch.no_grad()
    def count_seen_only(self, c2w: torch.Tensor, intrinsics: torch.Tensor, width: int, height: int,
                        near: float = 0.0, margin: float = 0.0) -> None:
        """From now on, :meth:`update` counts a sample point's density only where one of these
        cameras sees it: in its image grown by ``margin`` pixels on every side, in front of it
        and farther than ``near`` from it. A training ray samples no other point, so density
        there is what the field extrapolates beside the images; held-out views see it as
        floaters in the cells that an image holds only at its border.

        Args:
            c2w: [N, 3, 4] or [N, 4, 4] (or one) float camera-to-world matrices, OpenGL convention.
            intrinsics: [N, 4] (or [4]) float ``fx, fy, cx, cy`` in pixels.
            width, height: image size in pixels.
            near: distance from a camera (world units, ≥ 0) where its rays start.
            margin: pixels (≥ 0) by which the pinhole projection may miss a distorted lens's pixel.
        """
        check_distances(near=near, margin=margin)
        self._seen_c2w, self._seen_intrinsics = _camera_rows(c2w, intrinsics, width, height, self.occs.device)
        self._seen_frame = (float(width), float(height), float(near), float(margin))

    def _draw(self, lo: int, m: int, warmup: bool, n_uniform: int, seed: int,
              prefix: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """Cells [m] int32 and jittered points [m, 3] float32 of draws lo .. lo + m of an update."""
        cells = torch.empty(m, dtype=torch.int32, device=self.occs.device)
        points = torch.empty(m, 3, dtype=torch.float32, device=self.occs.device)
        _wp.launch(
            K.sample_cells, m,
            [lo, int(warmup), n_uniform, self.n_cells, seed, prefix,
             self.aabb, self.resolution, cells, points],
            _wp.device_of(self.occs),
        )
        return cells, points

    def _zero_unseen(self, points: torch.Tensor, values: torch.Tensor) -> None:
        """Set to 0, in place, the ``values`` [m] float32 of the world ``points`` [m, 3] float32
        that none of :meth:`count_seen_only`'s cameras sees."""
        _wp.launch(K.zero_unseen, points.shape[0], [points, self._seen_c2w, self._seen_intrinsics,
                                                    self._seen_c2w.shape[0], *self._seen_frame, values],
                   _wp.device_of(values))

    def _pack(self) -> None:
        _wp.launch(
            K.pack_bitfield, self.bitfield.numel(),
            [self.occs, self.threshold, self.n_cells, self.bitfield], _wp.device_of(self.occs),
        )
        self._pack_mips()

    def _pack_mips(self) -> None:
        device = _wp.device_of(self.bitfield)
        for m in range(1, self.n_mips + 1):
            _wp.launch(
                K.pack_mip, self.levels * (self.resolution >> m) ** 3,
                [self.bitfield, self.resolution, m, self.mip_cells, self._mip_bases[m - 2] if m > 1 else 0,
                 self._mip_bases[m - 1], self.mips], device,
            )
        self._mips_key = _storage_key(self.bitfield)

    def march_mips(self) -> torch.Tensor:
        """``mips``, rebuilt first if ``bitfield`` changed in place since they were built."""
        if self._mips_key is None or self._mips_key != _storage_key(self.bitfield):
            self._pack_mips()
        return self.mips

    def extra_repr(self) -> str:
        inner = f", contraction={self.contraction!r}, inner_aabb={self._inner_host}" if self.contraction else ""
        return f"aabb={self._aabb_host}, resolution={self.resolution}, levels={self.levels}{inner}"
