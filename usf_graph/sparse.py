"""Quiet use of torch's sparse CSR tensors, and the rules for what a layer keeps from call
to call."""

from __future__ import annotations

import contextlib
import warnings

import torch


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


def buffer_as(module: torch.nn.Module, name: str, dtype: torch.dtype) -> torch.Tensor:
    """Buffer ``name`` of ``module`` in ``dtype``, converted once: geometry kept in float64
    would otherwise be copied to a float32 call's dtype on every call. The copy is kept
    while the buffer is the same tensor (``.to()`` replaces it) at the same version."""
    t = getattr(module, name)
    v = version(t)
    if t.dtype == dtype or v is None:
        return t.to(dtype)
    cache = module.__dict__.setdefault("_buffers_as", {})
    hit = cache.get((name, dtype))
    if hit is not None and hit[0] is t and hit[1] == v:
        return hit[2]
    with kept():
        out = t.to(dtype)
    cache[(name, dtype)] = (t, v, out)
    return out
