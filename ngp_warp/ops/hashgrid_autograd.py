"""The hash-grid encoding's autograd: the torch.autograd.Function the eager path (and training)
runs, and a torch.library op that ``torch.compile`` traces without graph breaks, both over the
kernels of :class:`ngp_warp.HashGridEncoding`. Both are differentiable once: a second derivative
raises (:mod:`ngp_warp.ops._differentiable_once`)."""

from __future__ import annotations

import torch

from ngp_warp.ops._differentiable_once import SECOND_DERIVATIVE, outside_torch_func, plain, refuse_second_derivative
from ngp_warp.ops.op_registry import lookup


OP = "HashGridEncoding"


class HashGridFunction(torch.autograd.Function):
    """Encode ``x`` [N, D] float32 with ``params`` through ``enc``'s kernels. In the
    ``setup_context`` form, so that torch.func's grad and vmap take it."""

    @staticmethod
    def forward(x, params, enc):
        return enc._encode(x, params)

    @staticmethod
    def setup_context(ctx, inputs, output):
        x, params, enc = inputs
        ctx.enc = enc
        ctx.save_for_backward(x, params)

    @staticmethod
    def vmap(info, in_dims, x, params, enc):
        """Under torch.func.vmap: points batched over a dimension are one longer list of points
        (each point is encoded on its own); a batch of tables is encoded one table at a time."""
        x_dim, params_dim, _ = in_dims
        if params_dim is not None:
            xs = [x] * info.batch_size if x_dim is None else x.unbind(x_dim)
            return torch.stack([HashGridFunction.apply(xi, p, enc) for xi, p in zip(xs, params.unbind(params_dim))]), 0
        x = x.movedim(x_dim, 0)
        out = HashGridFunction.apply(x.reshape(-1, x.shape[-1]).contiguous(), params, enc)
        return out.reshape(*x.shape[:-1], out.shape[-1]), 0

    @staticmethod
    def backward(ctx, grad_out):
        x, params = ctx.saved_tensors
        enc = ctx.enc
        need_x, need_params = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        px, pp, grad = plain(x, OP), plain(params, OP), plain(grad_out, OP)
        with torch.no_grad(), outside_torch_func():  # the kernels on plain tensors, torch.func's wrappers off
            grad = aligned(grad.contiguous())
            grad_x = enc._grad_x(px, pp, grad) if need_x else None
            grad_params = enc._grad_params(px, grad) if need_params else None
        # under create_graph the results are tied to the inputs, so that a second derivative raises
        return (*refuse_second_derivative(OP, (grad_x, grad_params), (x, params, grad_out)), None)


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
    raise RuntimeError(SECOND_DERIVATIVE.format(op=OP))


_encode_op.register_autograd(_encode_op_backward, setup_context=_save)
_encode_backward_op.register_autograd(_refuse, setup_context=lambda ctx, inputs, output: None)
