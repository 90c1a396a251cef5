"""The sparse kernel's plain form, which autograd differentiates to any order: what
``torch.export`` traces, and what the fast forms' backward passes take when a gradient must
itself be differentiable (``create_graph=True``: gradient penalties, Hessian-vector
products)."""

from __future__ import annotations

import torch

from ..sparse import padded_values


def plain_aggregate(x: torch.Tensor, weight: torch.Tensor, coef: torch.Tensor,
                    plan) -> torch.Tensor:
    """:func:`~usf_graph.nn.aggregate.basis_aggregate` (``plan``: its
    :class:`~usf_graph.nn.aggregate.EdgePlan`) in its plain form (:func:`usf_graph.tracing.plain_forms`):
    each centre's neighbours gathered into a row padded to the most, one batched product
    with the coefficients, one with the weights. No sparse tensors and fixed shapes, so
    ``torch.export`` and ONNX take it; differentiable through autograd."""
    cols, slot = plan.padded()
    K, c_in, c_out = weight.shape
    B, N = x.shape[:2]
    if coef.dim() == 3:
        return torch.cat([plain_aggregate(x[b:b + 1], weight, coef[b], plan) for b in range(B)])
    a = padded_values(coef.to(x.dtype), slot).transpose(1, 2)  # [N, K, D]
    g = x.transpose(0, 1).index_select(0, cols.view(-1)).view(N, cols.shape[1], B * c_in)  # [N, D, B C_in]
    agg = (a @ g).view(N, K, B, c_in).permute(2, 0, 1, 3)  # [B, N, K, C_in]
    return agg.reshape(B, N, K * c_in) @ weight.reshape(K * c_in, c_out)


def differentiable_backward(ctx, grad: torch.Tensor) -> tuple:
    """A fast form's backward (``ctx`` saved ``x, weight, coef`` and the ``plan``) as
    autograd's own through :func:`plain_aggregate`, so that the gradients it returns are
    differentiable in the inputs and in ``grad``; their fast backward computes only first
    derivatives."""
    x, weight, coef = ctx.saved_tensors
    need = ctx.needs_input_grad[:3]
    with torch.enable_grad():
        out = plain_aggregate(x, weight, coef, ctx.plan)
    found = iter(torch.autograd.grad(out, [t for t, n in zip((x, weight, coef), need) if n],
                                     grad, create_graph=True))
    return tuple(next(found) if n else None for n in need) + (None,)
