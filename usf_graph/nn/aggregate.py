"""The sparse kernel of distance-only convolutions: ``y_b = sum_k A_k x_b W_k``.

:class:`EdgePlan` holds the sparsity structure of a graph's K aggregation matrices, in
buffers, computed once from ``edge_index`` alone. The values (the per-edge coefficients
``[E, K]``) are an input of every call, so one structure serves any mask, any kernel
and any coefficients that need gradients.
"""

from __future__ import annotations

import weakref

import torch
from torch import nn

from ..sparse import csr_indices, kept, padded_rows, quiet_sparse, row_pointers, version
from ..tracing import plain_forms, require_eager
from .plain import differentiable_backward, plain_aggregate
from .precision import accumulate_in
from .wide import wide_aggregate

TILE_ROWS = 16384  # rows per tile; 1k-16k measured, 16k fastest (benchmarks/README.md)
#: Which form :func:`basis_aggregate` takes. ``None``: one sparse product per call
#: (:mod:`usf_graph.nn.wide`) on a GPU, where launches are what costs, and one product per
#: (sample, tile, basis) block on the CPU, where caches are; ``True``/``False`` force one.
WIDE: bool | None = None


class EdgePlan(nn.Module):
    r"""The CSR structure of ``A [N, N]`` with ``A[i, j]`` for every edge ``(j -> i)``, and of
    its transpose, split into tiles of rows.

    A tile holds rows ``s:e`` restricted to the columns they reach (its halo). On a grid
    numbered along a space-filling curve, tiles of :data:`TILE_ROWS` rows keep every
    temporary in cache, so the time per point stays flat when ``[N, C]`` no longer fits;
    without locality (halos adding up to more than twice the points) there is one tile.
    Everything is derived from ``edge_index`` and ``num_nodes`` and kept in non-persistent
    buffers, so it follows ``.to()`` and is never matched to other inputs by address.

    Args:
        edge_index: ``[2, E]``, row 0 the neighbour j and row 1 the centre i.
        num_nodes: N.
        tile_rows: rows per tile (default :data:`TILE_ROWS`).
    """

    def __init__(self, edge_index: torch.Tensor, num_nodes: int, tile_rows: int | None = None):
        super().__init__()
        n, tile_rows = int(num_nodes), TILE_ROWS if tile_rows is None else int(tile_rows)
        j, i = edge_index.to(torch.long)
        key = i * n + j
        # graphs from geodesic_radius_graph (and PyG batches of them) are already row-major
        sorted_ = key.numel() < 2 or bool((key[1:] >= key[:-1]).all())
        order = None if sorted_ else torch.argsort(key)
        self.register_buffer("order", order, persistent=False)
        self.register_buffer("edge_index", edge_index, persistent=False)
        self.num_nodes, self.num_edges = n, int(key.numel())
        self.tile_rows = tile_rows
        self.wide_cache: dict = {}  # the one-product form's structures (nn.wide.structure)
        self._bounds: list | None = None  # the tiling: built by the first blockwise call
        self._memo: dict = {}  # the last coefficients' tiles, without and with transposes

    @property
    def bounds(self) -> list:
        """``(s, e, a, b, width)`` per tile: rows ``s:e``, sorted edges ``a:b``, halo width.
        Built on first use: the one-product form (:mod:`usf_graph.nn.wide`) never tiles,
        so a plan built per call on a GPU skips the tiling's per-tile syncs."""
        if self._bounds is None:
            with kept():
                self._tile()
        return self._bounds

    def _tile(self) -> None:
        n, tile_rows = self.num_nodes, self.tile_rows
        row, col = self.sorted_edges()
        blocks = [(0, n, 0, len(row), None)]
        if n >= 4 * tile_rows:
            starts = torch.arange(0, n + tile_rows, tile_rows, device=row.device).clamp_max(n)
            cuts = torch.searchsorted(row, starts).tolist()
            halos, total = [], 0
            for a, b in zip(cuts[:-1], cuts[1:]):  # stop as soon as the halos are too wide
                halos.append(torch.unique(col[a:b]))
                total += len(halos[-1])
                if total > 2 * n:
                    break
            if total <= 2 * n:
                blocks = [(int(starts[t]), int(starts[t + 1]), cuts[t], cuts[t + 1], h)
                          for t, h in enumerate(halos)]
        bounds = []
        for t, (s, e, a, b, cols) in enumerate(blocks):
            r, c = row[a:b] - s, col[a:b]
            width = n
            if cols is not None:
                c, width = torch.searchsorted(cols, c), len(cols)
            bounds.append((s, e, a, b, width))
            crow, c = csr_indices(_crow(r, e - s), c, width)
            for name, value in (("cols", cols), ("row", r), ("col", c), ("crow", crow),
                                ("perm_t", None), ("crow_t", None), ("col_t", None)):
                self.register_buffer(f"{name}{t}", value, persistent=False)
        self._bounds = bounds

    def matches(self, edge_index: torch.Tensor, num_nodes: int) -> bool:
        """Whether this plan was built for ``edge_index`` on ``num_nodes`` points (by value)."""
        return num_nodes == self.num_nodes and edge_index.shape == self.edge_index.shape and \
            bool(torch.equal(edge_index.to(self.edge_index.device), self.edge_index))

    def sorted_edges(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(row, col)``: every edge's centre i and neighbour j, sorted row-major."""
        j, i = self.edge_index.to(torch.long)
        return (i, j) if self.order is None else (i[self.order], j[self.order])

    def padded(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(cols [N, D], slot [N, D])``: every centre's neighbours in a row padded to the
        most (:func:`usf_graph.sparse.padded_rows`), ``slot`` indexing the edges in their
        given order (``E`` for padding). What the plain form reads; built on first use."""
        if getattr(self, "pad_col", None) is None:
            require_eager("plain forms' tables")
            with kept():
                row, col = self.sorted_edges()
                cols, slot = padded_rows(_crow(row, self.num_nodes), col)
                slot = slot[:, 0]
                if self.order is not None:  # sorted position -> given position
                    slot = torch.cat([self.order, self.order.new_tensor([self.num_edges])])[slot].int()
            self.register_buffer("pad_col", cols, persistent=False)
            self.register_buffer("pad_slot", slot, persistent=False)
        return self.pad_col, self.pad_slot

    def _transpose(self, t: int) -> None:
        """The transposed structure of tile ``t``, built when a backward pass first needs it
        (inference never does)."""
        if getattr(self, f"perm_t{t}") is not None:
            return
        s, e, _, _, width = self.bounds[t]
        r, c = getattr(self, f"row{t}"), getattr(self, f"col{t}")
        with kept():
            perm_t = torch.argsort(c.long() * (e - s) + r)  # row-major in the transpose
            crow_t, col_t = csr_indices(_crow(c, width), r[perm_t], e - s)
            setattr(self, f"perm_t{t}", perm_t)
            setattr(self, f"crow_t{t}", crow_t)
            setattr(self, f"col_t{t}", col_t)

    def tiles(self, coef: torch.Tensor, transpose: bool = False) -> list:
        """The tiles ``(s, e, cols, row, col, A, At)`` with ``A`` (and, with ``transpose``,
        ``At``; else None) tuples of K sparse CSR matrices holding ``coef [E, K]`` (edges
        in ``edge_index`` order). The last coefficients' tiles are kept while they are the
        same tensor at the same version: a layer's cached coefficients (one graph and
        mask, call after call) are sorted into tiles once."""
        v = version(coef)
        if v is None:  # an inference tensor: nothing to check a kept entry against
            return self._tiles(coef, transpose)
        memo = self._memo.get(transpose)
        if memo is not None and memo[0]() is coef and memo[1] == v:
            return memo[2]
        with kept():
            out = self._tiles(coef, transpose)
        self._memo[transpose] = (weakref.ref(coef, _dropper(self._memo, transpose)), v, out)
        return out

    def __getstate__(self) -> dict:
        # the kept tiles are sparse tensors (no storage to copy) behind weak references
        # (not picklable): a copy or a pickle starts without them
        return {**super().__getstate__(), "_memo": {}}

    def _tiles(self, coef: torch.Tensor, transpose: bool) -> list:
        c = coef if self.order is None else coef.index_select(0, self.order)
        cT = c.t().contiguous()  # [K, E]: each basis's values contiguous
        out = []
        with quiet_sparse():
            for t, (s, e, a, b, width) in enumerate(self.bounds):
                g = lambda name, t=t: getattr(self, f"{name}{t}")  # noqa: E731
                v = cT[:, a:b]
                A = tuple(torch.sparse_csr_tensor(g("crow"), g("col"), v[k], (e - s, width))
                          for k in range(len(cT)))
                At = None
                if transpose:
                    self._transpose(t)
                    vt = v.index_select(1, g("perm_t"))  # 3-4x faster than v[:, perm]
                    At = tuple(torch.sparse_csr_tensor(g("crow_t"), g("col_t"), vt[k],
                                                       (width, e - s)) for k in range(len(cT)))
                out.append((s, e, g("cols"), g("row"), g("col"), A, At))
        return out

    def extra_repr(self) -> str:
        tiles = "not built yet" if self._bounds is None else len(self._bounds)
        return f"num_nodes={self.num_nodes}, num_edges={self.num_edges}, tiles={tiles}"


def _dropper(memo: dict, key):
    """A weak reference's callback that frees ``memo[key]`` when its coefficients die (a
    sample's slice, a call's coefficients that need gradients: they never come back), unless
    a newer entry has taken the key."""
    def drop(ref):
        entry = memo.get(key)
        if entry is not None and entry[0] is ref:
            memo.pop(key, None)
    return drop


def _crow(rows: torch.Tensor, n: int) -> torch.Tensor:
    """CSR row pointers of sorted row indices."""
    return row_pointers(torch.bincount(rows, minlength=n))


def basis_aggregate(x: torch.Tensor, weight: torch.Tensor, coef: torch.Tensor,
                    plan: EdgePlan) -> torch.Tensor:
    r"""``y_b = sum_k A_bk (x_b W_k)``: ``x [B, N, C_in]``, ``weight [K, C_in, C_out]``,
    ``coef [E, K]`` shared by the batch or ``[B, E, K]`` per sample (``A_bk[i, j]`` of
    edge ``j -> i``) -> ``[B, N, C_out]``. Differentiable in ``x``, ``weight`` and ``coef``.
    The form follows :data:`WIDE`. Half-precision inputs are summed in float32 and the
    result returned in their dtype (:func:`~usf_graph.nn.precision.accumulate_in`)."""
    K = weight.shape[0]
    if coef.shape[-2:] != (plan.num_edges, K) or coef.dim() not in (2, 3) or \
            (coef.dim() == 3 and len(coef) != len(x)):
        raise ValueError(f"coef must be [{plan.num_edges}, {K}] or [{len(x)}, {plan.num_edges}, "
                         f"{K}], got {tuple(coef.shape)}")
    acc = accumulate_in(x.dtype)
    if acc != x.dtype:
        return basis_aggregate(x.to(acc), weight.to(acc), coef.to(acc), plan).to(x.dtype)
    if plain_forms(x, weight, coef):
        return plain_aggregate(x, weight, coef, plan)
    if WIDE or (WIDE is None and x.device.type != "cpu"):
        return wide_aggregate(x, weight, coef, plan)
    if coef.dim() == 3:  # one sample at a time: each has its own matrices
        return torch.cat([_BasisAggregate.apply(x[b:b + 1], weight, coef[b], plan)
                          for b in range(len(x))])
    return _BasisAggregate.apply(x, weight, coef, plan)


class _BasisAggregate(torch.autograd.Function):
    r"""One (sample, tile, basis) block at a time, so temporaries stay small (the stacked
    ``[N*K, N]`` form cost more in page faults and copies than in arithmetic). The sparse
    products dominate and cost in proportion to their column count, so the order follows
    the narrower side. Mixing first (``C_out`` columns), the backward pass shares one
    ``P = At_k g_b`` between ``dx_b = sum_k P W_k^T`` and ``dW_k = sum_b x_b^T P``.
    Aggregating first (``C_in`` columns: ``U = A_k x_b`` forward, recomputed backward, and
    ``At_k (g_b W_k^T)``) wins when ``3 C_in < 2 C_out``, e.g. on a narrow input. The
    coefficients' gradient is a sampled product: ``dA_k[i, j] = sum_b <g_b[i], (x_b W_k)[j]>``.
    """

    @staticmethod
    def forward(ctx, x, weight, coef, plan):
        B, N, c_in = x.shape
        c_out = weight.shape[2]
        ctx.aggregate_first = agg = 3 * c_in < 2 * c_out
        tiles = plan.tiles(coef)
        out = x.new_zeros(B, N, c_out)
        width, rows = _extent(tiles, N)
        xbuf = x.new_empty(width, c_in)  # buffers reused by every block
        z = x.new_empty(rows, c_in) if agg else x.new_empty(width, c_out)
        with quiet_sparse():
            for b in range(B):
                for s, e, cols, _, _, A, _ in tiles:
                    xw = _gather(x[b], cols, xbuf)
                    ob = out[b, s:e]
                    for k, A_k in enumerate(A):
                        if agg:
                            zk = z[:e - s]
                            torch.addmm(zk, A_k, xw, beta=0, out=zk)
                            ob.addmm_(zk, weight[k])
                        else:
                            zk = z[:len(xw)]
                            torch.mm(xw, weight[k], out=zk)
                            ob.addmm_(A_k, zk)
        ctx.save_for_backward(x, weight, coef)
        ctx.plan = plan
        return out

    @staticmethod
    def backward(ctx, grad):
        if torch.is_grad_enabled():  # create_graph=True: a gradient to differentiate again
            return differentiable_backward(ctx, grad)
        x, weight, coef = ctx.saved_tensors
        plan = ctx.plan
        tiles = plan.tiles(coef, transpose=True)
        grad = grad.contiguous()
        need_x, need_w, need_c = ctx.needs_input_grad[:3]
        gx = torch.zeros_like(x) if need_x else None
        gw = torch.zeros_like(weight) if need_w else None
        gc = coef.new_zeros(coef.shape) if need_c else None  # row-major edge order
        N, c_in, c_out = x.shape[1], x.shape[2], weight.shape[2]
        width, rows = _extent(tiles, N)
        xbuf, gbuf = x.new_empty(width, c_in), x.new_empty(width, c_in)
        u = x.new_empty(rows, c_in) if ctx.aggregate_first else x.new_empty(width, c_out)
        q = x.new_empty(rows, c_in)
        with quiet_sparse():
            for b in range(x.shape[0]):
                for t, (s, e, cols, r, c, A, At) in enumerate(tiles):
                    a0, a1 = plan.bounds[t][2:4]
                    xw = _gather(x[b], cols, xbuf)
                    gb = grad[b, s:e]
                    gxw = None if not need_x else gx[b] if cols is None else \
                        gbuf[:len(cols)].zero_()
                    for k, At_k in enumerate(At):
                        # q = g_b W_k^T, shared by the coefficients' gradient (when C_in is
                        # the narrower side of <g W_k^T, x> = <g, x W_k>) and by dx when
                        # aggregating first
                        qk = None
                        if (need_c and c_in <= c_out) or (need_x and ctx.aggregate_first):
                            qk = torch.mm(gb, weight[k].t(), out=q[:e - s])
                        if need_c:
                            gc[a0:a1, k] += (qk.index_select(0, r) * xw.index_select(0, c)).sum(-1) \
                                if qk is not None else (gb.index_select(0, r) * (xw @ weight[k])
                                                        .index_select(0, c)).sum(-1)
                        if not (need_x or need_w):
                            continue
                        if ctx.aggregate_first:
                            uk = u[:e - s]
                            if need_w:
                                torch.addmm(uk, A[k], xw, beta=0, out=uk)
                                gw[k].addmm_(uk.t(), gb)
                            if need_x:
                                gxw.addmm_(At_k, qk)
                            continue
                        p = u[:len(xw)]
                        torch.addmm(p, At_k, gb, beta=0, out=p)
                        if need_w:
                            gw[k].addmm_(xw.t(), p)
                        if need_x:
                            gxw.addmm_(p, weight[k].t())
                    if need_x and cols is not None:
                        gx[b].index_add_(0, cols, gxw)
        if need_c and plan.order is not None:
            gc = torch.empty_like(gc).index_copy_(0, plan.order, gc)
        return gx, gw, gc, None


def _extent(tiles, n: int) -> tuple[int, int]:
    """The widest halo and the most rows of any tile: the sizes of the reused buffers."""
    return (max(n if t[2] is None else len(t[2]) for t in tiles),
            max(t[1] - t[0] for t in tiles))


def _gather(x: torch.Tensor, cols: torch.Tensor | None, buf: torch.Tensor) -> torch.Tensor:
    """``x[cols]`` into ``buf`` (``x`` itself when ``cols`` is None)."""
    if cols is None:
        return x
    return torch.index_select(x, 0, cols, out=buf[:len(cols)])
