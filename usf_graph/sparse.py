"""Quiet use of torch's sparse CSR tensors, and the rules for what a layer keeps from call
to call."""

from __future__ import annotations

import contextlib
import warnings

import torch

from .tracing import exporting


@contextlib.contextmanager
def quiet_sparse():
    """Around sparse products: silence torch's "Sparse CSR tensor support is in beta" and
    "Sparse invariant checks" UserWarnings, raised on every construction and use (other
    warnings still show), and keep autocast out: it would cast the products to half
    precision, which the CPU's sparse kernels lack; they run in the dtype their caller
    chose (:func:`usf_graph.nn.precision.accumulate_in`)."""
    with warnings.catch_warnings(), contextlib.ExitStack() as stack:
        warnings.filterwarnings("ignore", message="Sparse", category=UserWarning)
        for device in ("cpu", "cuda"):
            if torch.is_autocast_enabled(device):
                stack.enter_context(torch.autocast(device, enabled=False))
        yield


@contextlib.contextmanager
def kept():
    """For values a layer keeps from call to call (coefficients, tiles, converted
    buffers): made without autograd history and never as inference tensors, even inside
    ``torch.inference_mode()``. An inference tensor has no version counter to check a
    cache against, and a later training call could not save it for backward."""
    with torch.inference_mode(False), torch.no_grad():
        yield


def version(t: torch.Tensor) -> int | None:
    """``t``'s version counter (in-place edits bump it); None for an inference tensor,
    which has none, so nothing may be kept on its account."""
    return None if t.is_inference() else t._version


class _Apply(torch.autograd.Function):
    """``A @ x`` for a constant sparse ``A`` whose transpose is precomputed: torch's own
    backward transposes the CSR matrix (a sort) on every call."""

    @staticmethod
    def forward(ctx, x, A, At):
        ctx.At = At
        with quiet_sparse():
            return A @ x

    @staticmethod
    def backward(ctx, grad):
        with quiet_sparse():
            return ctx.At @ grad.contiguous(), None, None


def sparse_apply(A: torch.Tensor, At: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``A @ x`` (``x`` dense ``[N, C]``), differentiable in ``x`` through ``At = A^T``."""
    return _Apply.apply(x, A, At)


def padded_rows(crow: torch.Tensor, col: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The entries of a CSR matrix ``[R, M]`` laid out in rows padded to the longest:
    ``(col [R, D], slot [R, D])``, ``slot`` the entry's index (``nnz`` for padding, which
    reads a zero appended to the values, and column 0). Built once, eagerly."""
    crow, col = crow.long(), col.long()
    r, nnz = len(crow) - 1, len(col)
    counts = crow.diff()
    d = int(counts.max()) if r and nnz else 0
    row = torch.repeat_interleave(torch.arange(r, device=col.device), counts)
    pos = torch.arange(nnz, device=col.device) - crow[row]
    slot = torch.full((r, d), nnz, dtype=torch.long, device=col.device)
    slot[row, pos] = torch.arange(nnz, device=col.device)
    cols = torch.zeros((r, d), dtype=torch.long, device=col.device)
    cols[row, pos] = col
    return cols, slot


def padded_values(val: torch.Tensor, slot: torch.Tensor) -> torch.Tensor:
    """``val [nnz, ...]`` laid out as :func:`padded_rows`' ``slot``: ``[R, D, ...]``, 0 in
    the padding."""
    return torch.cat([val, val.new_zeros(1, *val.shape[1:])])[slot]


def padded_matmul(cols: torch.Tensor, slot: torch.Tensor, val: torch.Tensor,
                  x: torch.Tensor) -> torch.Tensor:
    """``A @ x`` for ``A`` in :func:`padded_rows`' layout (values ``val [nnz]``) and a dense
    ``x [M, ...]`` -> ``[R, ...]``: one gather and one batched product, without sparse
    tensors or scatters, so ``torch.export`` and ONNX take it and run it fast."""
    w = padded_values(val.to(x.dtype), slot)  # [R, D]
    g = x.index_select(0, cols.view(-1)).view(*cols.shape, -1)  # [R, D, F]
    return (w[:, None, :] @ g)[:, 0].reshape(len(cols), *x.shape[1:])


def csr(row: torch.Tensor, col: torch.Tensor, val: torch.Tensor, shape) -> torch.Tensor:
    """A sparse CSR matrix from COO entries (duplicates summed)."""
    with quiet_sparse():
        return torch.sparse_coo_tensor(torch.stack([row, col]), val, shape).coalesce() \
            .to_sparse_csr()


def csr_parts(A: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(crow, col, val)`` of a sparse CSR matrix, each with storage of its own: kept as
    dense buffers, members that alias the sparse tensor would stop ``torch.compile``
    (Dynamo cannot take a view whose base is sparse as a graph input)."""
    return A.crow_indices().clone(), A.col_indices().clone(), A.values().clone()


def transpose_csr(A: torch.Tensor) -> torch.Tensor:
    """The transpose of a sparse CSR matrix, as CSR."""
    with quiet_sparse():
        return A.t().to_sparse_coo().coalesce().to_sparse_csr()


def padded_layout(module: torch.nn.Module, name: str) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`padded_rows` of ``module``'s CSR buffers ``{name}_crow``/``{name}_col`` (or
    ``crow``/``col`` for ``name=""``), built on first use and kept in non-persistent
    buffers, so that they follow ``.to()`` and an exported graph holds them."""
    pre = f"{name}_" if name else ""
    if not hasattr(module, f"{pre}pad_col"):
        if exporting():
            raise RuntimeError("plain forms are built by an eager call first: export inside "
                               "usf_graph.tracing.fixed_fields, after one eager call there")
        with kept():
            cols, slot = padded_rows(getattr(module, f"{pre}crow"), getattr(module, f"{pre}col"))
        module.register_buffer(f"{pre}pad_col", cols, persistent=False)
        module.register_buffer(f"{pre}pad_slot", slot, persistent=False)
    return getattr(module, f"{pre}pad_col"), getattr(module, f"{pre}pad_slot")


def buffer_as(module: torch.nn.Module, name: str, dtype: torch.dtype) -> torch.Tensor:
    """Buffer ``name`` of ``module`` in ``dtype``, converted once: geometry kept in float64
    would otherwise be copied to a float32 call's dtype on every call. The copy is kept
    while the buffer is the same tensor (``.to()`` replaces it) at the same version."""
    t = getattr(module, name)
    v = version(t)
    if t.dtype == dtype or v is None or exporting():  # a traced call converts in its graph
        return t.to(dtype)
    cache = module.__dict__.setdefault("_buffers_as", {})
    hit = cache.get((name, dtype))
    if hit is not None and hit[0] is t and hit[1] == v:
        return hit[2]
    with kept():
        out = t.to(dtype)
    cache[(name, dtype)] = (t, v, out)
    return out
