"""Quiet use of torch's sparse CSR tensors, and the rules for what a layer keeps from call
to call."""

from __future__ import annotations

import contextlib
import warnings
import weakref

import torch

from .tracing import exporting, require_eager, transforming

#: Index counts below this take int32 indices; larger ones int64.
INT32_LIMIT = 2 ** 31


def index_dtype(*counts: int) -> torch.dtype:
    """The dtype of a CSR matrix's row pointers and columns whose sizes and entry count are
    ``counts``: int32 where they fit. torch's CPU sparse products (MKL) take int32 indices
    and convert int64 ones on every product (two copies a call: 9% of a bare product, up
    to 4% of a network's forward pass; ``benchmarks/sparse_indices.py``); int32 also
    halves their memory."""
    return torch.int32 if max(counts, default=0) < INT32_LIMIT else torch.int64


def csr_indices(crow: torch.Tensor, col: torch.Tensor, num_cols: int
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """``(crow, col)`` in :func:`index_dtype` for ``num_cols`` columns."""
    idx = index_dtype(len(crow), len(col), num_cols)
    return crow.to(idx), col.to(idx)


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
    cache against, and a later training call could not save it for backward. Nor, under a
    ``torch.func`` transform, as the transform's wrappers: they would outlive it in the
    caches (an exported program could not save them as constants)."""
    with torch.inference_mode(False), torch.no_grad(), contextlib.ExitStack() as stack:
        if transforming():
            stack.enter_context(torch._C._DisableFuncTorch())
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


def padded_rows(crow: torch.Tensor, col: torch.Tensor, group: int = 1
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """The entries of a CSR matrix ``[R, M]`` laid out in rows padded to the longest:
    ``(col [R/g, D], slot [R/g, g, D])``, int32, ``slot`` the entry's index (``nnz`` for
    padding, which reads a zero appended to the values; its column is 0). Consecutive
    blocks of ``group`` rows (g) that hold the same columns in the same order (the
    derivatives of one point) share one row of columns, so a product gathers once for
    them; a matrix whose blocks differ is laid out with g = 1. Built once, eagerly."""
    crow, col = crow.long(), col.long()
    r, nnz = len(crow) - 1, len(col)
    counts = crow.diff()
    row = entry_rows(counts)
    pos = torch.arange(nnz, device=col.device) - crow[row]  # each entry's place in its row
    if group > 1 and r % group == 0 and nnz:
        same = bool((counts.view(-1, group) == counts[::group, None]).all())
        # each entry against the entry at its place in its block's first row
        if not (same and bool((col[crow[:-1:group][row // group] + pos] == col).all())):
            group = 1
    else:
        group = 1
    d = int(counts.max()) if r and nnz else 0
    slot = torch.full((r, d), nnz, dtype=torch.int32, device=col.device)
    slot[row, pos] = torch.arange(nnz, dtype=torch.int32, device=col.device)
    cols = torch.zeros((r, d), dtype=torch.int32, device=col.device)
    cols[row, pos] = col.int()
    return cols[::group].contiguous(), slot.view(r // group, group, d)


def entry_rows(counts: torch.Tensor) -> torch.Tensor:
    """The row of every entry of a CSR matrix whose rows hold ``counts [R]`` entries."""
    return torch.repeat_interleave(torch.arange(len(counts), device=counts.device), counts)


def row_pointers(counts: torch.Tensor) -> torch.Tensor:
    """The CSR row pointers ``[R + 1]`` of rows that hold ``counts [R]`` entries."""
    return torch.cat([counts.new_zeros(1), counts.cumsum(0)])


def padded_values(val: torch.Tensor, slot: torch.Tensor) -> torch.Tensor:
    """``val [nnz, ...]`` laid out as :func:`padded_rows`' ``slot``: ``[*slot.shape, ...]``,
    0 in the padding."""
    full = torch.cat([val, val.new_zeros(1, *val.shape[1:])])
    return full.index_select(0, slot.reshape(-1)).view(*slot.shape, *val.shape[1:])


def csr(row: torch.Tensor, col: torch.Tensor, val: torch.Tensor, shape) -> torch.Tensor:
    """A sparse CSR matrix from COO entries (duplicates summed). Entries without
    duplicates are sorted into place with one argsort (half the time of coalescing them,
    which the rare graph with repeated edges still takes)."""
    key = row.long() * int(shape[1]) + col.long()
    order = torch.argsort(key)
    k = key[order]
    with quiet_sparse():
        if k.numel() > 1 and bool((k[1:] == k[:-1]).any()):
            return torch.sparse_coo_tensor(torch.stack([row, col]), val, shape).coalesce() \
                .to_sparse_csr()
        crow = row_pointers(torch.bincount(row.long(), minlength=int(shape[0])))
        return torch.sparse_csr_tensor(crow, col.long()[order], val[order], shape)


def csr_parts(A: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(crow, col, val)`` of a sparse CSR matrix, each with storage of its own (indices in
    :func:`index_dtype`): kept as dense buffers, members that alias the sparse tensor
    would stop ``torch.compile`` (Dynamo cannot take a view whose base is sparse as a
    graph input)."""
    crow, col = csr_indices(A.crow_indices(), A.col_indices(), A.shape[1])
    return crow.clone(), col.clone(), A.values().clone()


def transpose_csr(A: torch.Tensor) -> torch.Tensor:
    """The transpose of a sparse CSR matrix, as CSR."""
    with quiet_sparse():
        return A.t().to_sparse_csr()  # CSC to CSR: a third faster than through COO


_PADDED: dict = {}  # id of a CSR values buffer -> (a weak reference to it, its layout)


def padded_operator(module: torch.nn.Module, name: str, dtype: torch.dtype, group: int = 1
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """``module``'s CSR matrix (buffers ``{name}_crow``, ``_col``, ``_val``; ``crow``,
    ``col``, ``val`` for ``name=""``) in :func:`padded_rows`' layout: ``(cols [R/g, D],
    weights [R/g, g, D] in dtype)``, for :func:`padded_product`. Built on first use
    in each dtype and kept in non-persistent buffers, so that they follow ``.to()`` and an
    exported graph holds them as constants; a traced call cannot build them."""
    pre = f"{name}_" if name else ""
    key = f"{pre}pad_w_{str(dtype).rsplit('.', 1)[-1]}"
    if not hasattr(module, key):
        require_eager("plain forms' tables")
        crow, col, val = (getattr(module, f"{pre}{part}") for part in ("crow", "col", "val"))
        # modules that share one operator (the jets of one graph) share its layout too
        ref, entry = _PADDED.get(id(val), (None, None))
        stamp = (version(crow), version(col), version(val), group)
        if ref is None or ref() is not val or entry[0] != stamp:
            with kept():
                entry = (stamp, *padded_rows(crow, col, group), {})
            if version(val) is not None:
                k = id(val)
                _PADDED[k] = (weakref.ref(val, lambda _, k=k: _PADDED.pop(k, None)), entry)
        if dtype not in entry[3]:
            with kept():
                entry[3][dtype] = padded_values(val.to(dtype), entry[2])
        module.register_buffer(f"{pre}pad_col", entry[1], persistent=False)
        module.register_buffer(key, entry[3][dtype], persistent=False)
    return getattr(module, f"{pre}pad_col"), getattr(module, key)


def padded_product(cols: torch.Tensor, weights: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``A @ x`` for ``A`` as :func:`padded_operator` gives it and a dense ``x [M, ...]`` ->
    ``[R, ...]`` in ``weights``' dtype: one gather and one batched product. An ``x`` of
    another dtype (an image's uint8 pixels) is gathered as it is and converted after, which
    moves a quarter of the bytes."""
    flat = x.reshape(len(x), -1)
    g = flat.index_select(0, cols.view(-1)).view(*cols.shape, flat.shape[1])  # [R/g, D, F]
    return (weights @ g.to(weights.dtype)).reshape(weights.shape[0] * weights.shape[1], *x.shape[1:])


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
