"""Hand-written backward kernels are differentiable once: :func:`refuse_second_derivative`
ties their gradients to every tensor they were computed from, so that differentiating through
them again (``create_graph=True``, then another ``grad``) raises instead of silently dropping
the second-order terms. torch's ``once_differentiable`` alone does not: it refuses only when
the incoming gradient itself requires grad, and treats the saved inputs as constants."""

from __future__ import annotations

import torch
from torch._C import _functorch
from torch._functorch.pyfunctorch import temporarily_clear_interpreter_stack as outside_torch_func


SECOND_DERIVATIVE = ("{op}'s backward is a hand-written Warp kernel, differentiable once: a second derivative "
                     "through it is not supported (float64 inputs run the pure-torch twin, which is differentiable "
                     "to any order)")


class _Refused(torch.autograd.Function):
    """Identity on the gradients; its own backward raises (one line naming the op)."""

    @staticmethod
    def forward(op: str, n_grads: int, *tensors):
        return tuple(t.clone() for t in tensors[:n_grads])

    @staticmethod
    def setup_context(ctx, inputs, output):  # the torch.func style, so that its transforms take it
        ctx.op = inputs[0]

    @staticmethod
    def backward(ctx, *_):
        raise RuntimeError(SECOND_DERIVATIVE.format(op=ctx.op))


def refuse_second_derivative(op: str, grads: tuple, sources: tuple) -> tuple:
    """``grads`` (tensors or None) as they are; under ``create_graph`` with any of ``sources``
    (the forward's inputs and the incoming gradients, None allowed) requiring grad, the same
    values whose backward raises."""
    if not torch.is_grad_enabled() or not any(isinstance(t, torch.Tensor) and t.requires_grad for t in sources):
        return grads
    present = [g for g in grads if g is not None]
    tied = iter(_Refused.apply(op, len(present), *present,
                               *[t for t in sources if isinstance(t, torch.Tensor) and t.requires_grad]))
    return tuple(None if g is None else next(tied) for g in grads)


def plain(t: torch.Tensor | None, op: str = "composite") -> torch.Tensor | None:
    """``t`` without torch.func's gradient-tracking wrappers (a Warp launch needs storage);
    ValueError for a vmapped (batched) tensor, whose extra dimension the kernels would misread."""
    while t is not None and _functorch.is_functorch_wrapped_tensor(t):
        if _functorch.is_batchedtensor(t):
            raise ValueError(f"{op}'s Warp backward cannot be vmapped (torch.func.jacrev, jacfwd, vmap of a "
                             "gradient): use torch.func.grad per output, or float64 inputs (the pure-torch twin)")
        t = _functorch.get_unwrapped(t)
    return t
