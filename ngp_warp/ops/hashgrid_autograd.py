"""The hash-grid encoding's autograd: the torch.autograd.Function the eager path (and training)
runs, and a torch.library op that ``torch.compile`` traces without graph breaks, both over the
kernels of :class:`ngp_warp.HashGridEncoding`. Both are differentiable once: a second derivative
raises (:mod:`ngp_warp.ops._differentiable_once`)."""

from __future__ import annotations

import torch

from ngp_warp.ops._differentiable_once import SECOND_DERIVATIVE, refuse_second_derivative
from ngp_warp.ops.op_registry import lookup


class HashGridFunction(torch.autograd.Function):
    """Encode ``x`` [N, D] float32 with ``params`` through ``enc``'s kernels."""

    @staticmethod
    def forward(ctx, x, params, enc):
        ctx.enc = enc
        ctx.save_for_backward(x, params)
        return enc._encode(x, params)

    @staticmethod
    def backward(ctx, grad_out):
        x, params = ctx.saved_tensors
        enc = ctx.enc
        need_x, need_params = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        if torch.is_grad_enabled():  # create_graph: the kernels' results are tied, and refuse a second derivative
            with torch.no_grad():
                grads = HashGridFunction.backward(ctx, grad_out)[:2]
            return (*refuse_second_derivative("HashGridEncoding", grads, (x, params, grad_out)), None)
        grad = aligned(grad_out.contiguous())
        grad_x = enc._grad_x(x, params, grad) if need_x else None
        grad_params = enc._grad_params(x, grad) if need_params else None
        return grad_x, grad_params, None


def aligned(t: torch.Tensor) -> torch.Tensor:
    """``t`` itself when 16-byte aligned (the kernels use vector loads), else an aligned copy."""
    return t if t.data_ptr() % 16 == 0 else t.clone()


def compiled_encode(enc, x: torch.Tensor, params: torch.Tensor) -> torch.Tensor:
    """The encoding through the torch.library op (for torch.compile): [N, L*F] float32."""
    return _encode_op(x, params, id(enc))


@torch.library.custom_op("ngp_warp::hash_grid_encode", mutates_args=())
def _encode_op(x: torch.Tensor, params: torch.Tensor, encoding: int) -> torch.Tensor:
    return lookup(encoding)._encode(x, params)


@_encode_op.register_fake
def _(x, params, encoding):
    return x.new_empty(x.shape[0], lookup(encoding).n_output_dims)


@torch.library.custom_op("ngp_warp::hash_grid_encode_backward", mutates_args=())
def _encode_backward_op(x: torch.Tensor, params: torch.Tensor, grad_out: torch.Tensor,
                        encoding: int) -> tuple[torch.Tensor, torch.Tensor]:
    enc, grad = lookup(encoding), aligned(grad_out.contiguous())
    return enc._grad_x(x, params, grad), enc._grad_params(x, grad)


@_encode_backward_op.register_fake
def _(x, params, grad_out, encoding):
    return torch.empty_like(x), torch.empty_like(params)


def _save(ctx, inputs, output):
    ctx.save_for_backward(inputs[0], inputs[1])
    ctx.encoding = inputs[2]


def _encode_op_backward(ctx, grad_out):
    x, params = ctx.saved_tensors
    grad_x, grad_params = _encode_backward_op(x, params, grad_out, ctx.encoding)
    return grad_x, grad_params, None


def _refuse(ctx, *_):
    raise RuntimeError(SECOND_DERIVATIVE.format(op="HashGridEncoding"))


_encode_op.register_autograd(_encode_op_backward, setup_context=_save)
_encode_backward_op.register_autograd(_refuse, setup_context=lambda ctx, inputs, output: None)
