"""Differentiable front-to-back compositing of packed samples (Warp forward and backward).

For the samples :math:`i` of one ray, front to back,

.. math::

    \\alpha_i = 1 - e^{-\\sigma_i (t^{end}_i - t^{start}_i)}, \\quad
    T_i = \\prod_{j<i} (1 - \\alpha_j), \\quad
    w_i = T_i \\alpha_i \\;[T_i \\ge \\epsilon],

    C = \\sum_i w_i c_i, \\quad O = \\sum_i w_i, \\quad
    D = \\sum_i w_i \\frac{t^{start}_i + t^{end}_i}{2}.

Gradients flow to :math:`\\sigma`, :math:`c` and the intervals (through
:math:`\\sigma_i (t^{end}_i - t^{start}_i)` and the depth's midpoints) through a hand-written
backward kernel, to first order: a second derivative through it raises (one line) rather than
return a silently wrong value (:mod:`ngp_warp.ops._differentiable_once`). float64 samples go through the
pure-torch float64 twin (:mod:`ngp_warp._reference.composite`), which autograd differentiates
to any order, e.g. for ``torch.autograd.gradcheck``.
"""

from __future__ import annotations

import torch

from ngp_warp import _wp
from ngp_warp.ops._differentiable_once import SECOND_DERIVATIVE, plain as _plain, refuse_second_derivative
from ngp_warp._reference import composite as reference
from ngp_warp.kernels import composite as K

# CUDA block size of this module's kernels: one thread walks a whole ray, and a batch has ~10^4
# rays, so small blocks spread them over all multiprocessors.
_BLOCK = 32


def launch_forward(sigmas, rgbs, t_starts, t_ends, ray_offsets, early_stop_eps: float):
    """The forward kernel: (rgb [N, 3], opacity [N], depth [N], weights [S], trans [S]) float32,
    the transmittance in front of each sample kept for the backward."""
    sigmas, rgbs, t_starts, t_ends, ray_offsets = map(_plain, (sigmas, rgbs, t_starts, t_ends, ray_offsets))
    n_rays, n_samples = ray_offsets.shape[0] - 1, sigmas.shape[0]
    dev = sigmas.device
    rgb = torch.empty(n_rays, 3, dtype=torch.float32, device=dev)
    opacity = torch.empty(n_rays, dtype=torch.float32, device=dev)
    depth = torch.empty(n_rays, dtype=torch.float32, device=dev)
    trans = torch.empty(n_samples, dtype=torch.float32, device=dev)
    weights = torch.zeros(n_samples, dtype=torch.float32, device=dev)  # padding rows stay 0
    _wp.launch(
        K.composite_forward, n_rays,
        [sigmas, rgbs, t_starts, t_ends, ray_offsets, float(early_stop_eps), rgb, opacity, depth, trans, weights],
        _wp.device_of(sigmas), block_dim=_BLOCK,
    )
    return rgb, opacity, depth, weights, trans


def launch_backward(sigmas, rgbs, t_starts, t_ends, ray_offsets, trans, g_rgb, g_opacity, g_depth, g_weights,
                    interval_grads: bool = False):
    """The backward kernel: (dL/dσ [S], dL/dc [S, 3], dL/dt_start [S], dL/dt_end [S]) float32
    from the gradients of rgb, opacity, depth and weights (each None when absent), computed
    without autograd; the intervals' two are None unless ``interval_grads``."""
    sigmas, rgbs, t_starts, t_ends, ray_offsets, trans = map(_plain, (sigmas, rgbs, t_starts, t_ends, ray_offsets,
                                                                       trans))
    grads = [None if g is None else _plain(g.detach().float().contiguous()) for g in (g_rgb, g_opacity, g_depth,
                                                                                       g_weights)]
    has_grads = sum(1 << k for k, g in enumerate(grads) if g is not None)
    # Zeros: padding rows past the last ray (see ngp_warp.ops.prune) get no gradient. (Under
    # torch.func.grad new tensors come wrapped too: the kernel writes through to their storage.)
    grad_sigmas, grad_rgbs = torch.zeros_like(sigmas), torch.zeros_like(rgbs)
    grad_t = (torch.zeros_like(t_starts), torch.zeros_like(t_ends)) if interval_grads else (None, None)
    if has_grads:
        _wp.launch(
            K.composite_backward, ray_offsets.shape[0] - 1,
            [sigmas, rgbs, t_starts, t_ends, ray_offsets, trans, *grads, has_grads | (16 if interval_grads else 0),
             _plain(grad_sigmas), _plain(grad_rgbs), *map(_plain, grad_t)],
            _wp.device_of(sigmas), block_dim=_BLOCK,
        )
    return grad_sigmas, grad_rgbs, *grad_t


def _loop_vmap(apply, info, in_dims, args):
    """A ``torch.func.vmap`` rule that calls ``apply`` once per batch entry and stacks the
    outputs along dimension 0."""
    outputs = []
    for k in range(info.batch_size):
        outputs.append(apply(*[a.select(d, k) if d is not None else a for a, d in zip(args, in_dims)]))
    stacked = tuple(torch.stack(parts) for parts in zip(*outputs))
    return stacked, (0,) * len(stacked)


class _Composite(torch.autograd.Function):
    """Compositing with the Warp forward and hand-written backward kernels, for eager calls
    (``torch.compile`` and meta tensors take the torch.library op below, which costs tens of
    microseconds more per call on the host). Forward returns ``trans`` as a fifth,
    non-differentiable output, kept for the backward."""

    @staticmethod
    def forward(sigmas, rgbs, t_starts, t_ends, ray_offsets, early_stop_eps: float):
        return launch_forward(sigmas, rgbs, t_starts, t_ends, ray_offsets, early_stop_eps)

    @staticmethod
    def setup_context(ctx, inputs, output):  # the torch.func style: grad and jvp-free transforms work
        ctx.save_for_backward(*inputs[:5], output[4])
        ctx.mark_non_differentiable(output[4])
        ctx.set_materialize_grads(False)

    @staticmethod
    def vmap(info, in_dims, sigmas, rgbs, t_starts, t_ends, ray_offsets, early_stop_eps):
        """A batch of sample sets, one call each (the kernels take one set)."""
        return _loop_vmap(_Composite.apply, info, in_dims, (sigmas, rgbs, t_starts, t_ends, ray_offsets,
                                                            early_stop_eps))

    @staticmethod
    def backward(ctx, g_rgb, g_opacity, g_depth, g_weights, _g_trans):
        saved = ctx.saved_tensors  # checks for in-place changes
        incoming = (g_rgb, g_opacity, g_depth, g_weights)
        if all(g is None for g in incoming):
            return None, None, None, None, None, None
        grads = launch_backward(*saved, *incoming, interval_grads=any(ctx.needs_input_grad[2:4]))
        grads = refuse_second_derivative("composite", grads, (*saved[:4], *incoming))
        return *grads, None, None


# The op as torch.compile and meta tensors see it, registered with torch.library: opaque (no
# graph breaks, no tracing into Warp), fake kernels for shapes, a backward that refuses a second
# derivative. Eager calls keep the leaner autograd.Function above.
@torch.library.custom_op("ngp_warp::composite", mutates_args=())
def _composite_op(sigmas: torch.Tensor, rgbs: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor,
                  ray_offsets: torch.Tensor, early_stop_eps: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor,
                                                                               torch.Tensor, torch.Tensor]:
    return launch_forward(sigmas, rgbs, t_starts, t_ends, ray_offsets, early_stop_eps)


@_composite_op.register_fake
def _(sigmas, rgbs, t_starts, t_ends, ray_offsets, early_stop_eps):
    n_rays, n_samples = ray_offsets.shape[0] - 1, sigmas.shape[0]
    return (sigmas.new_empty(n_rays, 3), sigmas.new_empty(n_rays), sigmas.new_empty(n_rays),
            sigmas.new_empty(n_samples), sigmas.new_empty(n_samples))


@torch.library.custom_op("ngp_warp::composite_backward", mutates_args=())
def _composite_backward_op(sigmas: torch.Tensor, rgbs: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor,
                           ray_offsets: torch.Tensor, trans: torch.Tensor, g_rgb: torch.Tensor,
                           g_opacity: torch.Tensor, g_depth: torch.Tensor,
                           g_weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """As :func:`launch_backward`, the intervals' gradients always computed (an op's schema takes
    no flag that inductor's generated backward keeps; autograd drops what is not needed)."""
    return launch_backward(sigmas, rgbs, t_starts, t_ends, ray_offsets, trans, g_rgb, g_opacity, g_depth, g_weights,
                           interval_grads=True)


@_composite_backward_op.register_fake
def _(sigmas, rgbs, t_starts, t_ends, ray_offsets, trans, g_rgb, g_opacity, g_depth, g_weights):
    return torch.empty_like(sigmas), torch.empty_like(rgbs), torch.empty_like(t_starts), torch.empty_like(t_ends)


def _save_inputs(ctx, inputs, output):
    ctx.save_for_backward(*inputs[:5], output[4])


def _composite_op_backward(ctx, g_rgb, g_opacity, g_depth, g_weights, _g_trans):
    return *_composite_backward_op(*ctx.saved_tensors, g_rgb, g_opacity, g_depth, g_weights), None, None


def _refuse(ctx, *_):
    raise RuntimeError(SECOND_DERIVATIVE.format(op="composite"))


_composite_op.register_autograd(_composite_op_backward, setup_context=_save_inputs)
_composite_backward_op.register_autograd(_refuse, setup_context=lambda ctx, inputs, output: None)


@torch.library.custom_op("ngp_warp::ray_offsets", mutates_args=())
def _ray_offsets_op(ray_indices: torch.Tensor, n_rays: int) -> torch.Tensor:
    return ray_offsets_from_indices(ray_indices, n_rays)


@_ray_offsets_op.register_fake
def _(ray_indices, n_rays):
    return ray_indices.new_empty(n_rays + 1, dtype=torch.int32)


def composite_packed(
    sigmas: torch.Tensor,
    rgbs: torch.Tensor,
    t_starts: torch.Tensor,
    t_ends: torch.Tensor,
    ray_offsets: torch.Tensor,
    early_stop_eps: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`ngp_warp.composite` on validated, contiguous float32 samples (S ≥ 1) given by
    ``ray_offsets`` [n_rays + 1] int32 (as from :func:`ngp_warp.ray_marching`), skipping the
    conversion from ray indices.

    Returns ``(rgb [n_rays, 3], opacity [n_rays], depth [n_rays], weights [S])``, all
    differentiable w.r.t. ``sigmas``, ``rgbs``, ``t_starts`` and ``t_ends``.
    """
    return _Composite.apply(sigmas, rgbs, t_starts, t_ends, ray_offsets, float(early_stop_eps))[:4]


def ray_offsets_from_indices(ray_indices: torch.Tensor, n_rays: int) -> torch.Tensor:
    """[S] int64 sorted ray indices → [n_rays + 1] int32 offsets, on the device, no sync."""
    if ray_indices.shape[0] == 0:
        return torch.zeros(n_rays + 1, dtype=torch.int32, device=ray_indices.device)
    offsets = torch.empty(n_rays + 1, dtype=torch.int32, device=ray_indices.device)
    _wp.launch(
        K.offsets_from_indices, ray_indices.shape[0], [ray_indices, ray_indices.shape[0], n_rays, offsets],
        _wp.device_of(ray_indices), block_dim=_BLOCK,
    )
    return offsets


_VALUE_PROBLEMS = (
    "ray_indices must lie in [0, n_rays)",
    "ray_indices must be sorted (the samples of each ray contiguous, front to back)",
    "t_starts and t_ends must be finite with t_ends ≥ t_starts",
    "sigmas must be finite and ≥ 0",
)


def _known_zero(n) -> bool:
    """Whether the sample count ``n`` is 0; under torch.compile, where it may be a size known only
    when the graph runs, False unless it is known to be 0. torch's symbolic shapes (and sympy)
    are imported only then."""
    if not torch.compiler.is_compiling():
        return n == 0
    from torch.fx.experimental.symbolic_shapes import guard_or_false
    return guard_or_false(n == 0)


def _check_values(sigmas, t_starts, t_ends, ray_indices, n_rays: int) -> None:
    """ValueError for the first of :data:`_VALUE_PROBLEMS` found in the S ≥ 1 samples (one sync)."""
    flags = torch.stack([
        ((ray_indices < 0) | (ray_indices >= n_rays)).any(),
        (ray_indices[1:] < ray_indices[:-1]).any(),
        ~(torch.isfinite(t_starts) & torch.isfinite(t_ends) & (t_ends >= t_starts)).all(),
        ~(torch.isfinite(sigmas) & (sigmas >= 0)).all(),
    ]).tolist()
    for bad, problem in zip(flags, _VALUE_PROBLEMS):
        if bad:
            raise ValueError(problem)


def composite(
    sigmas: torch.Tensor,
    rgbs: torch.Tensor,
    t_starts: torch.Tensor,
    t_ends: torch.Tensor,
    ray_indices: torch.Tensor,
    n_rays: int,
    early_stop_eps: float = 0.0,
    return_weights: bool = False,
    validate: bool = True,
):
    """Composite packed samples into per-ray colour, opacity and depth (see the module equations).

    Args:
        sigmas: [S] float32 densities σ ≥ 0. rgbs: [S, 3] float32 colours. float64 throughout
            (these and the intervals) runs the float64 twin instead of the kernels.
        t_starts, t_ends: [S] float32 sample intervals (differentiable: through
            :math:`\\sigma_i (t^{end}_i - t^{start}_i)` and the depth's midpoints).
        ray_indices: [S] int64 or int32, the ray of each sample, **sorted** (samples of a ray
            contiguous and front to back), each in ``[0, n_rays)``.
        n_rays: number of rays (rays without samples get zeros).
        early_stop_eps: samples with transmittance :math:`T_i < \\epsilon` contribute nothing.
        return_weights: also return the per-sample weights :math:`w_i` ([S] float32,
            differentiable).
        validate: check the values (one host sync): ray indices sorted and in range, finite
            intervals with ``t_ends ≥ t_starts``, σ ≥ 0; ValueError naming the first problem.
            Pass False where the samples come from :func:`ngp_warp.ray_marching` (or call
            :func:`composite_packed`).

    Returns:
        ``(rgb [n_rays, 3], opacity [n_rays], depth [n_rays])`` float32, plus ``weights [S]`` when
        ``return_weights``. Depth is not normalised by opacity.
    """
    if not isinstance(sigmas, torch.Tensor) or sigmas.dim() != 1:
        raise ValueError(f"sigmas must be a [S] tensor, got {getattr(sigmas, 'shape', type(sigmas).__name__)}")
    n_samples = sigmas.shape[0]
    expected = {"sigmas": (sigmas, (n_samples,)), "rgbs": (rgbs, (n_samples, 3)),
                "t_starts": (t_starts, (n_samples,)), "t_ends": (t_ends, (n_samples,))}
    for name, (t, shape) in expected.items():
        if not isinstance(t, torch.Tensor) or tuple(t.shape) != shape:
            raise ValueError(f"{name} must have shape {list(shape)}, got {getattr(t, 'shape', type(t).__name__)}")
        if t.dtype != sigmas.dtype or t.dtype not in (torch.float32, torch.float64):
            raise ValueError(f"{name} must be float32 (or float64 throughout, for the float64 twin), "
                             f"got {t.dtype} with sigmas {sigmas.dtype}")
        if t.device != sigmas.device:
            raise ValueError(f"{name} is on {t.device} but sigmas on {sigmas.device}")
    if not isinstance(ray_indices, torch.Tensor) or tuple(ray_indices.shape) != (n_samples,):
        raise ValueError(f"ray_indices must have shape [{n_samples}], got {getattr(ray_indices, 'shape', ray_indices)}")
    if ray_indices.dtype not in (torch.int64, torch.int32) or ray_indices.device != sigmas.device:
        raise ValueError(f"ray_indices must be int64/int32 on {sigmas.device}, got {ray_indices.dtype} on {ray_indices.device}")
    if not isinstance(n_rays, int) or n_rays < 0 or (n_rays == 0 and n_samples > 0):
        raise ValueError(f"n_rays must be a non-negative int (positive when there are samples), got {n_rays!r}")
    if early_stop_eps < 0:
        raise ValueError(f"early_stop_eps must be ≥ 0, got {early_stop_eps}")
    compiling = torch.compiler.is_compiling()
    if not compiling and sigmas.device.type != "meta":  # meta tensors: shapes only, through the fake kernels
        _wp.device_of(sigmas)  # CPU or CUDA only
    if _known_zero(n_samples):  # zeros, still in the inputs' graph (a loss on them can backward);
        # a count known only when the graph runs (a compiled march's) takes the op, which handles 0
        zero, dev, dtype = sigmas.sum() + rgbs.sum(), sigmas.device, sigmas.dtype
        out = tuple(torch.zeros(shape, device=dev, dtype=dtype) + zero for shape in ((n_rays, 3), n_rays, n_rays))
        return (*out, sigmas * 0) if return_weights else out
    if validate and not compiling and sigmas.device.type != "meta":  # reading the checks back is a host sync, which a compiled graph has not
        _check_values(sigmas, t_starts, t_ends, ray_indices, n_rays)
    if sigmas.dtype == torch.float64:
        out = reference.composite(sigmas, rgbs, t_starts, t_ends, ray_indices.to(torch.int64), n_rays, early_stop_eps)
        return out if return_weights else out[:3]
    parts = (sigmas.contiguous(), rgbs.contiguous(), t_starts.contiguous(), t_ends.contiguous())
    if compiling or sigmas.device.type == "meta":  # the torch.library ops: traced, or shapes only
        offsets = _ray_offsets_op(ray_indices.to(torch.int64).contiguous(), n_rays)
        rgb, opacity, depth, weights, _ = _composite_op(*parts, offsets, float(early_stop_eps))
    else:  # eager: the autograd Function (less host time; torch.func transforms, hence torch's search)
        queries = torch.arange(n_rays + 1, device=ray_indices.device, dtype=ray_indices.dtype)
        offsets = torch.searchsorted(ray_indices.contiguous(), queries, out_int32=True)
        rgb, opacity, depth, weights = composite_packed(*parts, offsets, early_stop_eps)
    return (rgb, opacity, depth, weights) if return_weights else (rgb, opacity, depth)
