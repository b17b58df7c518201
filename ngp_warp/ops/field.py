"""The instant-NGP radiance field: hash grid → density MLP, spherical harmonics → colour MLP.

.. math::

    h = \\mathrm{MLP}_\\sigma(\\mathrm{enc}(x)) \\in \\mathbb{R}^{16}, \\qquad
    \\sigma = \\exp(h_0), \\qquad
    c = \\mathrm{sigmoid}(\\mathrm{MLP}_c([h, \\mathrm{SH}_4(d)]))

Density depends on position only; colour on position and view direction.

Unbounded scenes (``contraction``): positions go through the scene contraction C of
:mod:`ngp_warp.ops.contraction` before the hash grid, whose box is then the contracted one,
[-2, 2]³, normalised to [0, 1]³ as (C(x) + 2) / 4; all of space is inside.

Per-image appearance (``FieldConfig.appearance_dim`` = A > 0, NeRF-W / nerfstudio style): a
learned code :math:`e_i \\in \\mathbb{R}^A` per training image joins the colour MLP's input,
:math:`c = \\mathrm{sigmoid}(\\mathrm{MLP}_c([h, \\mathrm{SH}_4(d), e_i]))`; density does not see it,
so it can change colour only (exposure, white balance). Views without a training image (test
views, renders) use the mean code over the training images.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

import warp as wp

from ngp_warp import _wp
from ngp_warp._checks import check_aabb_values, check_numbers
from ngp_warp.ops.contraction import KINDS, contract
from ngp_warp.ops.gather import embedding_rows
from ngp_warp.ops.hashgrid import HashGridEncoding
from ngp_warp.ops.spherical_harmonics import spherical_harmonics_deg4
from ngp_warp.kernels import field as K


INSTANT_NGP_FINEST_RESOLUTION = 2048.0  # instant-ngp's finest level over its unit cube
INSTANT_NGP_LOG2_HASHMAP_SIZE = 19      # instant-ngp's table size per level, 2^19 entries
MAX_RESOLUTION = float(1 << 24)         # a level's cells per axis: beyond, float32 grid coordinates lose cells
INITIAL_OPTICAL_DEPTH = 0.05            # of an untrained contracted field across its inner box


@dataclass
class FieldConfig:
    """Sizes of the NGP field (defaults: instant-ngp's NeRF configuration, except the finest
    resolution, which by default follows the training images' resolution)."""

    n_levels: int = 16
    n_features_per_level: int = 2
    log2_hashmap_size: int = INSTANT_NGP_LOG2_HASHMAP_SIZE
    base_resolution: int = 16
    finest_resolution: float | None = None  # None: the Trainer matches the training pixels
                                            # (pixel_matched_resolution); NGPField alone: 2048
    hidden: int = 64
    geo_features: int = 16
    appearance_dim: int | None = None  # per-image appearance code size A (0: none); None: the
                                       # Trainer picks per scene (16 for captures, 0 for
                                       # NeRF-synthetic; scene_defaults.appearance_dim); NGPField alone: 0
    environment: bool | None = None    # a learned colour at infinity per view direction (the
                                       # background); None: the Trainer's (on for contracted
                                       # fields, scene_defaults); NGPField alone: off

    def check(self) -> None:
        """Raise ValueError naming the first size outside its range (a None finest resolution or
        appearance code size is left to the Trainer)."""
        if self.appearance_dim is not None and (type(self.appearance_dim) is not int or self.appearance_dim < 0):
            raise ValueError(f"appearance_dim must be a non-negative int or None, got {self.appearance_dim!r}")
        if self.environment not in (None, True, False):
            raise ValueError(f"environment must be true, false or None, got {self.environment!r}")
        check_numbers(self, counts=("n_levels", "base_resolution", "hidden", "geo_features", "log2_hashmap_size"),
                      positive=("finest_resolution",), optional=("finest_resolution",))
        if self.n_features_per_level not in (1, 2, 4, 8) or type(self.n_features_per_level) is not int:
            raise ValueError(f"n_features_per_level must be 1, 2, 4 or 8, got {self.n_features_per_level!r}")
        if self.log2_hashmap_size > 30:
            raise ValueError(f"log2_hashmap_size must be at most 30, got {self.log2_hashmap_size}")
        if self.finest_resolution is not None and MAX_RESOLUTION < self.finest_resolution < math.inf:
            raise ValueError(f"finest_resolution must be at most 2^24 cells (grid coordinates are float32), "
                             f"got {self.finest_resolution:g}")
        if self.finest_resolution is not None and self.finest_resolution < self.base_resolution:
            raise ValueError(f"field.base_resolution {self.base_resolution} is above the finest level's "
                             f"{self.finest_resolution:g}: the levels would grow coarser")


class _TruncExp(torch.autograd.Function):
    """exp(x) whose gradient is exp(min(x, 15)): keeps early large log-densities from exploding."""

    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return torch.exp(x)

    @staticmethod
    def backward(ctx, g):
        (x,) = ctx.saved_tensors
        return g * torch.exp(x.clamp(max=15.0))


def trunc_exp(x: torch.Tensor) -> torch.Tensor:
    """Truncated exponential (instant-ngp's density activation)."""
    return _TruncExp.apply(x)


def density_from_log(log_sigma: torch.Tensor, positions: torch.Tensor, aabb: torch.Tensor) -> torch.Tensor:
    """σ = exp(h) at positions inside ``aabb``, 0 outside, in one Warp kernel (no gradient).
    Outside the box σ is 0 even where exp(h) overflows (``trunc_exp(h) * inside`` gives NaN).

    log_sigma: [N, 1] or [N] float32 or bfloat16 h, contiguous. positions: [N, 3] float32.
    aabb: [6] float32 on their device. Returns [N] float32.
    """
    n = positions.shape[0]
    if log_sigma.numel() != n or not log_sigma.is_contiguous() or log_sigma.dtype not in (torch.float32, torch.bfloat16):
        raise ValueError(f"log_sigma must be a contiguous float32 or bfloat16 [{n}] or [{n}, 1] tensor")
    sigma = torch.empty(n, dtype=torch.float32, device=positions.device)
    if log_sigma.dtype == torch.bfloat16:
        kernel, h = K.density_from_log_bf16, log_sigma.view(torch.int16).reshape(n)
    else:
        kernel, h = K.density_from_log, log_sigma.reshape(n)
    _wp.launch(kernel, n, [h, _wp.to_wp(positions, dtype=wp.vec3), aabb, sigma], _wp.device_of(positions))
    return sigma


def _contracted_density_shift(aabb: torch.Tensor) -> float:
    """s of σ = exp(h − s) for a contracted field: an untrained field (h ≈ 0) then has optical
    depth :data:`INITIAL_OPTICAL_DEPTH` across the inner box (σ₀ · 2 · its mean half side), so
    that rays start nearly transparent, as DVGO's ``alpha_init`` does for unbounded scenes:
    at σ = 1 everywhere the rays would stop within a world unit of the cameras, where the
    colours of each training view are then painted as a fog that no other view sees. h₀ also
    feeds the colour MLP, and a surface needs h₀ ≈ s + log σ (about 10 here): on 2 CPU cores
    the colours of the demo scene on white as a COLMAP model stalled at grey (training MSE 0.021
    from step 150 on), where depth 0.5 (s = 2.8) reached 0.0076 by step 300; on an H100 at
    60 s the smaller shift scored lower on four of five captures, one run each (RESULTS.md)."""
    half_side = float((aabb[3:] - aabb[:3]).mean()) / 2.0
    return math.log(2.0 * half_side / INITIAL_OPTICAL_DEPTH)


def _mlp(sizes: list[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        layers.append(nn.Linear(a, b, bias=False))
        if i < len(sizes) - 2:
            layers.append(nn.ReLU(inplace=True))
    return nn.Sequential(*layers)


def _mlp_no_grad(mlp: nn.Sequential, x: torch.Tensor, n_outputs: int | None = None) -> torch.Tensor:
    """x [N, in] through :func:`_mlp`'s layers in x's dtype, for no-autograd passes: each hidden
    layer's ReLU runs in its matmul's epilogue (``torch._addmm_activation``, cuBLASLt on CUDA),
    and the last layer computes only its first ``n_outputs`` outputs (None: all). [N, n_outputs]."""
    weights = [m.weight.to(x.dtype) for m in mlp if isinstance(m, nn.Linear)]
    for w in weights[:-1]:
        x = torch._addmm_activation(x.new_zeros(w.shape[0]), x, w.t())
    return torch.mm(x, weights[-1][:n_outputs].t())


class NGPField(nn.Module):
    """Hash-grid radiance field over an axis-aligned box.

    Args:
        aabb: [6] float ``(xmin, ymin, zmin, xmax, ymax, zmax)``; positions are mapped to
            [0, 1]^3 inside it before the hash grid. With ``contraction``, the inner box.
        config: :class:`FieldConfig`.
        contraction: None, ``"l2"`` or ``"linf"`` (:func:`ngp_warp.ops.contraction.contract`).
        n_images: training images, one appearance code each (needed when
            ``config.appearance_dim > 0``).
    """

    def __init__(self, aabb: torch.Tensor, config: FieldConfig | None = None, contraction: str | None = None,
                 n_images: int = 0):
        super().__init__()
        cfg = config or FieldConfig()
        if contraction is not None and contraction not in KINDS:
            raise ValueError(f"contraction must be None or one of {sorted(KINDS)}, got {contraction!r}")
        codes = cfg.appearance_dim or 0
        if codes > 0 and (type(n_images) is not int or n_images < 1):
            raise ValueError(f"appearance codes need n_images ≥ 1, got {n_images!r}")
        self.config = cfg
        self.contraction = contraction
        aabb = torch.as_tensor(aabb, dtype=torch.float32).reshape(6)
        check_aabb_values(aabb)  # once, here: not per call
        self.register_buffer("aabb", aabb.clone())
        # the hash grid's box: the field's box, or the contracted ball's [-2, 2]^3
        grid_box = aabb.clone() if contraction is None else torch.tensor([-2.0] * 3 + [2.0] * 3)
        self.register_buffer("grid_aabb", grid_box, persistent=False)
        self.density_shift = 0.0 if contraction is None else _contracted_density_shift(aabb)
        self.encoding = HashGridEncoding(
            n_input_dims=3,
            n_levels=cfg.n_levels,
            n_features_per_level=cfg.n_features_per_level,
            log2_hashmap_size=cfg.log2_hashmap_size,
            base_resolution=cfg.base_resolution,
            desired_resolution=cfg.finest_resolution or INSTANT_NGP_FINEST_RESOLUTION,
        )
        self.density_mlp = _mlp([self.encoding.n_output_dims, cfg.hidden, cfg.geo_features])
        self.color_mlp = _mlp([cfg.geo_features + 16 + codes, cfg.hidden, cfg.hidden, 3])
        self.appearance = None
        if codes > 0:
            self.appearance = nn.Embedding(n_images, codes)
            nn.init.normal_(self.appearance.weight, std=0.01)
        self.environment = None  # colour at infinity: sigmoid(W SH_4(d) + b), smooth by construction
        if cfg.environment:
            self.environment = nn.Linear(16, 3)
            nn.init.zeros_(self.environment.weight)
            nn.init.zeros_(self.environment.bias)

    def mlp_parameters(self) -> list[nn.Parameter]:
        """MLP weights, appearance codes and the environment (the ones that get weight decay)."""
        codes = [] if self.appearance is None else list(self.appearance.parameters())
        environment = [] if self.environment is None else list(self.environment.parameters())
        return list(self.density_mlp.parameters()) + list(self.color_mlp.parameters()) + codes + environment

    def background(self, directions: torch.Tensor) -> torch.Tensor:
        """The learned environment's colour [N, 3] float32 in (0, 1) along unit ``directions``
        [N, 3] float32: sigmoid(W SH_4(d) + b), degree-4 spherical harmonics (16 values), so it
        can hold a sky or a backdrop's colour, not a picture of the training views. Differentiable
        in W and b, in float32 under autocast too. Needs ``config.environment``."""
        if self.environment is None:
            raise ValueError("this field has no learned environment (FieldConfig.environment is off)")
        with torch.autocast(directions.device.type, enabled=False):
            return torch.sigmoid(self.environment(spherical_harmonics_deg4(directions)))

    def _grid_points(self, positions: torch.Tensor) -> torch.Tensor:
        """World positions [N, 3] → the hash grid's coordinates [N, 3] float32: themselves, or C(x)
        (which has no backward: positions that require grad are refused, as :func:`contract` does)."""
        if self.contraction is None:
            return positions
        return contract(positions.float().contiguous(), self.contraction, self.aabb, check_box=False)

    def _unit(self, grid_points: torch.Tensor) -> torch.Tensor:
        """Grid coordinates [N, 3] mapped from the (contracted) box to [0, 1]^3, contiguous (the
        encoding's input)."""
        lo, hi = self.grid_aabb[:3], self.grid_aabb[3:]
        return ((grid_points - lo) / (hi - lo)).contiguous()

    def _features(self, positions: torch.Tensor) -> torch.Tensor:
        return self.encoding(self._unit(self._grid_points(positions)))

    def _geometry(self, positions: torch.Tensor) -> torch.Tensor:
        return self.density_mlp(self._features(positions))

    def _geometry_no_grad(self, grid_points: torch.Tensor, n_outputs: int | None = None) -> torch.Tensor:
        """The density MLP's first ``n_outputs`` outputs (None: all G) [N, n_outputs] at grid
        coordinates [N, 3], through :func:`_mlp_no_grad`, in the autocast dtype when autocast is on
        (bfloat16 features come rounded from the kernel: half the bytes, no cast)."""
        x = self._unit(grid_points)
        autocast = x.is_cuda and torch.is_autocast_enabled("cuda")
        dtype = torch.get_autocast_dtype("cuda") if autocast else x.dtype
        features = self.encoding.encode(x, dtype if dtype == torch.bfloat16 else torch.float32).to(dtype)
        return _mlp_no_grad(self.density_mlp, features, n_outputs)

    def _sigma_no_grad(self, h: torch.Tensor, grid_points: torch.Tensor) -> torch.Tensor:
        """σ [N] float32 from the density MLP's output h [N, ≥1] (column 0, shifted by
        :attr:`density_shift` in float32 when there is one) at grid coordinates [N, 3], zero
        outside the box (:func:`density_from_log`)."""
        log_sigma = h[:, :1]
        if self.density_shift:
            log_sigma = log_sigma.float() - self.density_shift
        elif log_sigma.dtype not in (torch.float32, torch.bfloat16):  # e.g. float16 autocast
            log_sigma = log_sigma.float()
        return density_from_log(log_sigma.contiguous(), grid_points.contiguous(), self.grid_aabb)

    def _inside(self, positions: torch.Tensor) -> torch.Tensor:
        """[N] bool: inside the box (everywhere with a contraction)."""
        if self.contraction is not None:
            return torch.ones(positions.shape[0], dtype=torch.bool, device=positions.device)
        return ((positions >= self.aabb[:3]) & (positions <= self.aabb[3:])).all(-1)

    def _sigma(self, h: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
        """σ [N] float32 from the density MLP's output h [N, G] (its first column, shifted by
        :attr:`density_shift` when there is one; no extra op without), zero outside the box."""
        log_sigma = h[:, 0].float()
        if self.density_shift:
            log_sigma = log_sigma - self.density_shift
        return trunc_exp(log_sigma) * self._inside(positions)

    def density(self, positions: torch.Tensor) -> torch.Tensor:
        """σ at positions [N, 3] float32 → [N] float32 (zero outside the box). On CUDA without
        autograd, through :meth:`geometry`'s fused matmuls, computing the one output column σ
        needs (equal up to matmul rounding)."""
        if positions.is_cuda and not torch.is_grad_enabled():
            grid_points = self._grid_points(positions)
            return self._sigma_no_grad(self._geometry_no_grad(grid_points, 1), grid_points)
        h = self._geometry(positions)
        return self._sigma(h, positions)

    @torch.no_grad()
    def geometry(self, positions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """σ and the density MLP's whole output at positions, without autograd (inference).

        Each hidden layer's ReLU runs in its matmul's epilogue (``torch._addmm_activation``,
        cuBLASLt on CUDA); under CUDA autocast the MLP runs in its dtype, bfloat16 features
        coming rounded from the hash-grid kernel.

        Args:
            positions: [N, 3] float32 world positions.

        Returns:
            (sigma [N] float32, zero outside the box, as :meth:`density`; h [N, G] in the
            autocast dtype, else float32, G = ``config.geo_features``: :meth:`colour`'s input).
        """
        if positions.ndim != 2 or positions.shape[1] != 3 or positions.dtype != torch.float32:
            raise ValueError(f"positions must be [N, 3] float32, got {tuple(positions.shape)} {positions.dtype}")
        grid_points = self._grid_points(positions)
        h = self._geometry_no_grad(grid_points)
        return self._sigma_no_grad(h, grid_points), h

    def colour(self, h: torch.Tensor, directions: torch.Tensor,
               appearance_code: torch.Tensor | None = None, differentiable: bool = False) -> torch.Tensor:
        """The colour MLP, as :meth:`forward` computes it: without autograd (inference), or
        ``differentiable`` through the modules, so that gradients reach the colour MLP's
        weights, ``h`` and ``appearance_code`` (e.g. to fit a code to an image with the field
        frozen, :func:`ngp_warp.training.appearance_fit.fit_appearance_code`).

        Args:
            h: [N, G] density MLP outputs from :meth:`geometry` (the MLP runs in their dtype).
            directions: [N, 3] float32 unit view directions.
            appearance_code: [A] float32 code for every row (see :meth:`appearance_code`);
                None: the mean training code.
            differentiable: record the colour MLP for autograd (slower: the modules, not the
                fused no-grad path).

        Returns:
            rgb [N, 3] float32 in (0, 1).
        """
        n, g = h.shape[0], self.config.geo_features
        if h.ndim != 2 or h.shape[1] != g or tuple(directions.shape) != (n, 3):
            raise ValueError(f"colour needs h [N, {g}] and directions [N, 3], "
                             f"got {tuple(h.shape)} and {tuple(directions.shape)}")
        code = self.appearance_code(appearance_code)
        codes = [] if code is None else [code.expand(n, -1)]
        if differentiable:
            return self._colour_head(h, directions, codes, fused=False)
        with torch.no_grad():
            return self._colour_head(h, directions, codes, fused=True)

    def appearance_code(self, code: torch.Tensor | None) -> torch.Tensor | None:
        """The [A] float32 code to colour with, on the field's device: ``code`` itself, or the
        mean training code when None; None for a field without appearance codes. ValueError
        (one line) for a code of the wrong shape, or a code given to a field without codes."""
        if self.appearance is None:
            if code is not None:
                raise ValueError("appearance_code given, but this field has no appearance codes (appearance_dim 0)")
            return None
        if code is None:
            return self.appearance.weight.mean(0)
        a = self.appearance.embedding_dim
        if not isinstance(code, torch.Tensor) or tuple(code.shape) != (a,) or not code.is_floating_point():
            raise ValueError(f"appearance_code must be a [{a}] float tensor, got {getattr(code, 'shape', code)!r}")
        return code.to(self.aabb.device, torch.float32)

    def appearance_codes(self, image_indices: torch.Tensor | None, n: int, device) -> list[torch.Tensor]:
        """[] without appearance codes, else [[n, A]]: the codes of ``image_indices`` ([n] int64
        training-image indices), or the mean code when None."""
        if self.appearance is None:
            return []
        if image_indices is None:
            return [self.appearance.weight.mean(0, keepdim=True).expand(n, -1)]
        if image_indices.shape != (n,):
            raise ValueError(f"image_indices must be [{n}], got {tuple(image_indices.shape)}")
        return [embedding_rows(self.appearance.weight, image_indices.to(device=device, dtype=torch.long))]

    def forward(self, positions: torch.Tensor, directions: torch.Tensor,
                image_indices: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(σ [N] float32, zero outside the box; rgb [N, 3] float32) at positions [N, 3] seen along
        unit directions [N, 3], in training images ``image_indices`` ([N] int64; None: the mean
        appearance code; ignored without appearance codes)."""
        h = self._geometry(positions)
        sigma = self._sigma(h, positions)
        codes = self.appearance_codes(image_indices, h.shape[0], h.device)
        return sigma, self._colour_head(h, directions, codes, fused=False)

    def _colour_head(self, h: torch.Tensor, directions: torch.Tensor, codes: list[torch.Tensor],
                     fused: bool) -> torch.Tensor:
        """rgb [N, 3] float32 = sigmoid(MLP_c([h, SH(d), code])) from h [N, G], unit directions
        [N, 3] float32 and codes ([] or [[N, A]]), in h's dtype: through the modules (autograd)
        or, ``fused``, through :func:`_mlp_no_grad`."""
        sh = spherical_harmonics_deg4(directions).to(h.dtype)
        x = torch.cat([h, sh, *[c.to(h.dtype) for c in codes]], dim=-1)
        out = _mlp_no_grad(self.color_mlp, x) if fused else self.color_mlp(x)
        return torch.sigmoid(out.float())
