"""``once_differentiable`` for backward passes computed outside torch (PETSc, numpy).

A backward computed in numpy returns gradients without a graph, so a second
derivative (``torch.autograd.grad(..., create_graph=True)`` then another grad)
would silently miss the solve's second-order term.  torch's own
``torch.autograd.function.once_differentiable`` attaches its error to detached
copies of the gradients: ``.backward()`` reaches it, but
``torch.autograd.grad(y, inputs)`` prunes it and returns the incomplete
derivative.  This decorator joins the error to what the gradients really depend
on (the incoming gradients and the tensors saved for backward, e.g. the solution
x), so every second derivative that would need the missing term raises.
"""

from __future__ import annotations

import functools

import torch

__all__ = ["once_differentiable"]

_MESSAGE = (
    "trying to differentiate twice a function that was marked with @once_differentiable: "
    "the backward of a PETSc solve (or of its numpy products) has no second derivative; "
    "use mode='unrolled' for second derivatives of the truncated solver"
)


class _NotTwice(torch.autograd.Function):
    """Identity on a computed gradient, joined to the tensors it depends on."""

    @staticmethod
    def forward(ctx, gradient, *depends_on):
        return gradient.view_as(gradient)

    @staticmethod
    def backward(ctx, *grads):
        raise RuntimeError(_MESSAGE)


def once_differentiable(backward):
    """Decorate a `torch.autograd.Function.backward` that is not differentiable itself.

    The backward runs under ``no_grad``.  When it runs with ``create_graph=True``
    and its gradients depend on tensors that require grad, each returned tensor
    passes through a node whose own backward raises `RuntimeError`.
    """

    @functools.wraps(backward)
    def wrapper(ctx, *grads):
        if not torch.is_grad_enabled():  # the usual backward (no create_graph)
            return backward(ctx, *grads)
        with torch.no_grad():
            outputs = backward(ctx, *grads)
        tensors = [*grads, *ctx.saved_tensors]
        depends_on = [t for t in tensors if isinstance(t, torch.Tensor) and t.requires_grad]
        if not depends_on:
            return outputs
        return tuple(
            _NotTwice.apply(out, *depends_on) if isinstance(out, torch.Tensor) else out
            for out in outputs
        )

    return wrapper
