r"""The sparse kernel ``y_b = sum_k A_bk x_b W_k`` as one sparse product per call: the GPU form.

:func:`~usf_graph.nn.aggregate.basis_aggregate` works one (sample, basis) block at a time,
which keeps a 2-core CPU's temporaries in cache but costs a GPU one kernel launch per
block: on an H100 the spherical U-Net's step was launch-bound (about 2,700 launches, a
third of its wall time on the GPU; ``benchmarks/README.md``). Here every sample and every
basis function go into one block-diagonal CSR matrix, so a layer is one dense GEMM and
one sparse product forward, and the same backward, whatever the batch and K:

* mixing first: ``Z = x W`` with rows ``(b, j, k)``, then ``y = F Z`` with
  ``F[(b, i), (b, j, k)] = A_bk[i, j]``;
* aggregating first (a narrow input): ``U = G x`` with ``G[(b, k, i), (b, j)] =
  A_bk[i, j]``, then ``y = U W``.

The structures depend only on the plan's edges, the batch size and K; they are built once
(the sort of one sample's entries, tiled over the batch) and kept in the plan. The values
are the call's coefficients, gathered, so masks and coefficients that need gradients work
as on the blockwise path. The coefficients' gradient is a sampled product
(``torch.sparse.sampled_addmm``) on the same structure.
"""

from __future__ import annotations

import torch

from ..sparse import index_dtype, kept, quiet_sparse, row_pointers
from .plain import differentiable_backward


def _local(kind: str, row, col, n: int, K: int):
    """One sample's entries ``(r, c)`` of matrix ``kind`` for entries ``m = e K + k``,
    and the sample's row and column counts."""
    m = torch.arange(len(row) * K, device=row.device)
    e, k = m // K, m % K
    i, j = row[e], col[e]
    return {"F": (i, j * K + k, n, n * K), "FT": (k * n + j, i, K * n, n),
            "G": (k * n + i, j, K * n, n), "GT": (j, k * n + i, n, K * n)}[kind], m


def structure(plan, kind: str, batch: int, K: int, per_sample: bool, device) -> tuple:
    """``(crow, col, src, shape)`` of block-diagonal matrix ``kind`` (``F``, ``FT``, ``G``,
    ``GT``; the module docstring) for ``batch`` samples and K coefficients per edge:
    entry ``p`` holds ``coef.reshape(-1)[src[p]]`` of the coefficients sorted by the plan
    (``[E, K]``, or ``[B, E, K]`` when ``per_sample``). Cached in the plan."""
    key = (kind, batch, K, per_sample, str(device))
    hit = plan.wide_cache.get(key)
    if hit is not None:
        return hit
    with kept():
        out = _structure(plan, kind, batch, K, per_sample, device)
    if len(plan.wide_cache) >= 16:  # e.g. many batch sizes: drop the oldest
        plan.wide_cache.pop(next(iter(plan.wide_cache)))
    plan.wide_cache[key] = out
    return out


def _structure(plan, kind: str, batch: int, K: int, per_sample: bool, device) -> tuple:
    row, col = (t.to(device) for t in plan.sorted_edges())
    (r, c, rows, cols), m = _local(kind, row, col, plan.num_nodes, K)
    perm = torch.argsort(r * cols + c)
    counts = torch.bincount(r[perm], minlength=rows)
    crow0 = row_pointers(counts)
    nnz = len(perm)
    b = torch.arange(batch, device=device)[:, None]
    crow = torch.cat([(crow0[:-1][None] + b * nnz).reshape(-1), crow0.new_full((1,), batch * nnz)])
    idx = index_dtype(batch * rows, batch * cols, batch * nnz)
    return (crow.to(idx), (c[perm][None] + b * cols).reshape(-1).to(idx),
            (m[perm][None] + b * nnz * per_sample).reshape(-1),
            (batch * rows, batch * cols))


def _sorted_flat(coef: torch.Tensor, plan) -> torch.Tensor:
    """The coefficients in the plan's edge order (``[E, K]`` or ``[B, E, K]``)."""
    return coef if plan.order is None else coef.index_select(-2, plan.order)


def _matrix(struct, flat: torch.Tensor) -> torch.Tensor:
    crow, col, src, shape = struct
    return torch.sparse_csr_tensor(crow, col, flat[src], shape)


def wide_aggregate(x: torch.Tensor, weight: torch.Tensor, coef: torch.Tensor, plan) -> torch.Tensor:
    r"""``y_b = sum_k A_bk (x_b W_k)`` in one sparse product: ``x [B, N, C_in]``, ``weight
    [K, C_in, C_out]``, ``coef [E, K]`` shared by the batch or ``[B, E, K]`` per sample
    (edges in ``edge_index`` order) -> ``[B, N, C_out]``. Differentiable in all three; equal
    to :func:`~usf_graph.nn.aggregate.basis_aggregate` up to rounding."""
    return _WideAggregate.apply(x, weight, coef, plan)


class _WideAggregate(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, weight, coef, plan):
        B, N, c_in = x.shape
        K, _, c_out = weight.shape
        per_sample = coef.dim() == 3
        flat = _sorted_flat(coef, plan).reshape(-1)
        ctx.aggregate_first = agg = 3 * c_in < 2 * c_out  # the narrower side, as blockwise
        xf = x.reshape(B * N, c_in)
        with quiet_sparse():
            if agg:
                u = _matrix(structure(plan, "G", B, K, per_sample, x.device), flat) @ xf
                y = _by_sample(u, B, K, N) @ weight.reshape(K * c_in, c_out)
            else:
                z = (xf @ weight.transpose(0, 1).reshape(c_in, K * c_out)).view(B * N * K, c_out)
                y = _matrix(structure(plan, "F", B, K, per_sample, x.device), flat) @ z
        ctx.save_for_backward(x, weight, coef)
        ctx.plan = plan
        return y.view(B, N, c_out)

    @staticmethod
    def backward(ctx, grad):
        if torch.is_grad_enabled():  # create_graph=True: a gradient to differentiate again
            return differentiable_backward(ctx, grad)
        x, weight, coef = ctx.saved_tensors
        plan = ctx.plan
        B, N, c_in = x.shape
        K, _, c_out = weight.shape
        per_sample = coef.dim() == 3
        flat = _sorted_flat(coef, plan).reshape(-1)
        need_x, need_w, need_c = ctx.needs_input_grad[:3]
        xf, gf = x.reshape(B * N, c_in), grad.reshape(B * N, c_out)
        gx = gw = gc = None
        with quiet_sparse():
            if ctx.aggregate_first:
                w2 = weight.reshape(K * c_in, c_out)
                gu = _by_basis(gf @ w2.t(), B, K, N)  # [B K N, C_in]: dL/du_bk
                if need_x:
                    gx = _matrix(structure(plan, "GT", B, K, per_sample, x.device), flat) @ gu
                if need_w:
                    u = _matrix(structure(plan, "G", B, K, per_sample, x.device), flat) @ xf
                    gw = (_by_sample(u, B, K, N).t() @ gf).view(K, c_in, c_out)
                sampled = ("G", gu, xf)
            else:
                wh = weight.transpose(0, 1).reshape(c_in, K * c_out)
                if need_x or need_w:
                    p = _matrix(structure(plan, "FT", B, K, per_sample, x.device), flat) @ gf
                    p = _by_sample(p, B, K, N)  # [B N, K C_out]
                    gx = p @ wh.t() if need_x else None
                    gw = (xf.t() @ p).view(c_in, K, c_out).transpose(0, 1) if need_w else None
                sampled = ("F", gf, (xf @ wh).view(B * N * K, c_out)) if need_c else None
            if need_c:
                kind, left, right = sampled
                crow, col, src, shape = structure(plan, kind, B, K, per_sample, x.device)
                pattern = torch.sparse_csr_tensor(crow, col, flat.new_zeros(len(src)), shape)
                vals = torch.sparse.sampled_addmm(pattern, left, right.t(), beta=0).values()
                gc = flat.new_zeros(flat.shape).index_add_(0, src, vals).view(coef.shape)
                if plan.order is not None:
                    gc = torch.empty_like(gc).index_copy_(gc.dim() - 2, plan.order, gc)
        return (None if gx is None else gx.view(B, N, c_in),
                None if gw is None else gw.contiguous(), gc, None)


def _by_sample(t: torch.Tensor, B: int, K: int, N: int) -> torch.Tensor:
    """Rows ``(b, k, i)`` ``[B K N, C]`` -> rows ``(b, i)``, columns ``(k, c)``: ``[B N, K C]``."""
    return t.view(B, K, N, -1).transpose(1, 2).reshape(B * N, -1)


def _by_basis(t: torch.Tensor, B: int, K: int, N: int) -> torch.Tensor:
    """The inverse of :func:`_by_sample`: ``[B N, K C]`` -> ``[B K N, C]``."""
    return t.view(B, N, K, -1).transpose(1, 2).reshape(B * K * N, -1)
