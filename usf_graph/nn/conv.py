"""SphericalConv / PointConv: convolution with a kernel of distance only."""

from __future__ import annotations

import torch
from torch import nn
from torch.autograd.function import once_differentiable
from torch_geometric.nn import MessagePassing

from .kernel import DistanceKernel, envelope
from .sparse import csr

NORMALIZE = ("area", "mean", None)


TILE_ROWS = 16384  # rows per tile; 1k-16k measured, 16k fastest (benchmarks/README.md)


class _BasisConv(torch.autograd.Function):
    r"""``y_b = sum_k A_k (x_b W_k)`` for constant sparse ``A_k`` ``[N, N]`` and weights
    ``W`` ``[K, C_in, C_out]``, over a list of tiles.

    A tile ``(s, e, cols, A, At)`` holds rows ``s:e`` of every ``A_k`` restricted to the
    columns ``cols`` they reach (its halo; ``None``: all), and the transposes ``At``.
    One tile covering everything is the plain product; on a grid numbered along a
    space-filling curve, tiles of :data:`TILE_ROWS` rows keep every temporary in cache,
    so the time per point stays flat when ``[N, C]`` no longer fits.

    Working one (sample, tile, basis) block at a time keeps temporaries small (the
    stacked ``[N*K, N]`` form cost more in page faults and copies than in arithmetic).
    The sparse products dominate and cost in proportion to their column count, so the
    order follows the narrower side. Mixing first (``C_out`` columns), the backward pass
    shares one ``P = At_k g_b`` between ``dx_b = sum_k P W_k^T`` and
    ``dW_k = sum_b x_b^T P``. Aggregating first (``C_in`` columns: ``U = A_k x_b``
    forward, recomputed backward, and ``At_k (g_b W_k^T)``) wins when
    ``3 C_in < 2 C_out``, e.g. on a narrow input.
    """

    @staticmethod
    def forward(ctx, x, weight, tiles):
        B, N, c_in = x.shape
        c_out = weight.shape[2]
        ctx.aggregate_first = agg = 3 * c_in < 2 * c_out
        out = x.new_zeros(B, N, c_out)
        # buffers reused by every block: fresh [N, C] tensors cost page faults
        width, rows = _extent(tiles, N)
        xbuf = x.new_empty(width, c_in)
        z = x.new_empty(rows, c_in) if agg else x.new_empty(width, c_out)
        for b in range(B):
            for s, e, cols, A, _ in tiles:
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
        ctx.save_for_backward(x, weight)
        ctx.tiles = tiles
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        x, weight = ctx.saved_tensors
        grad = grad.contiguous()
        need_x, need_w = ctx.needs_input_grad[:2]
        gx = torch.zeros_like(x) if need_x else None
        gw = torch.zeros_like(weight) if need_w else None
        N, c_in, c_out = x.shape[1], x.shape[2], weight.shape[2]
        width, rows = _extent(ctx.tiles, N)
        xbuf, gbuf = x.new_empty(width, c_in), x.new_empty(width, c_in)
        u = x.new_empty(rows, c_in) if ctx.aggregate_first else x.new_empty(width, c_out)
        q = x.new_empty(rows, c_in)
        for b in range(x.shape[0]):
            for s, e, cols, A, At in ctx.tiles:
                xw = _gather(x[b], cols, xbuf)
                gb = grad[b, s:e]
                gxw = None if not need_x else gx[b] if cols is None else \
                    gbuf[:len(cols)].zero_()
                for k, At_k in enumerate(At):
                    if ctx.aggregate_first:
                        uk, qk = u[:e - s], q[:e - s]
                        if need_w:
                            torch.addmm(uk, A[k], xw, beta=0, out=uk)
                            gw[k].addmm_(uk.t(), gb)
                        if need_x:
                            torch.mm(gb, weight[k].t(), out=qk)
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
        return gx, gw, None


def _extent(tiles, n: int) -> tuple[int, int]:
    """The widest halo and the most rows of any tile: the sizes of the reused buffers."""
    return (max(n if t[2] is None else len(t[2]) for t in tiles),
            max(e - s for s, e, *_ in tiles))


def _gather(x: torch.Tensor, cols: torch.Tensor | None, buf: torch.Tensor) -> torch.Tensor:
    """``x[cols]`` into ``buf`` (``x`` itself when ``cols`` is None)."""
    if cols is None:
        return x
    return torch.index_select(x, 0, cols, out=buf[:len(cols)])


def plan_tiles(row: torch.Tensor, col: torch.Tensor, coef: torch.Tensor, n: int,
               tile_rows: int | None = None) -> list:
    """Tiles for :class:`_BasisConv` from the edges ``(row, col)`` and their ``[E, K]``
    coefficients: blocks of ``tile_rows`` rows (default :data:`TILE_ROWS`) with the
    columns they reach, or one tile when the numbering has no locality (the halos
    would add up to more than twice the points)."""
    tile_rows = TILE_ROWS if tile_rows is None else tile_rows
    order = torch.argsort(row * n + col)  # row-major: each block's edges are one slice
    row, col, coef = row[order], col[order], coef[order]
    blocks = [(0, n, 0, len(row), None)]
    if n >= 4 * tile_rows:
        starts = torch.arange(0, n + tile_rows, tile_rows).clamp_max(n)
        cuts = torch.searchsorted(row, starts).tolist()
        halos = [torch.unique(col[a:b]) for a, b in zip(cuts[:-1], cuts[1:])]
        if sum(len(h) for h in halos) <= 2 * n:
            blocks = [(int(starts[t]), int(starts[t + 1]), cuts[t], cuts[t + 1], h)
                      for t, h in enumerate(halos)]
    tiles = []
    for s, e, a, b, cols in blocks:
        r, c, v = row[a:b] - s, col[a:b], coef[a:b]
        width = n
        if cols is not None:
            c, width = torch.searchsorted(cols, c), len(cols)
        A = tuple(csr(r, c, v[:, k], (e - s, width)) for k in range(v.shape[1]))
        At = tuple(csr(c, r, v[:, k], (width, e - s)) for k in range(v.shape[1]))
        tiles.append((s, e, cols, A, At))
    return tiles


def _key(*tensors) -> tuple:
    return tuple((t.data_ptr(), t.shape, t.dtype, t._version) if t is not None else None
                 for t in tensors)


class DistanceConv(MessagePassing):
    r"""Convolution whose kernel depends only on the distance between points.

    .. math::
        \mathbf{y}_i = \sum_{k=1}^{K} \mathbf{W}_k^\top
        \frac{\sum_{j \in \mathcal{N}(i)} \phi_k(d_{ij})\, w_j\, \mathbf{x}_j}
             {\sum_{j \in \mathcal{N}(i)} w_j\, \phi(d_{ij})} + \mathbf{b},
        \qquad \phi = \textstyle\sum_k \phi_k

    with :math:`\phi_k` from :class:`DistanceKernel`, :math:`d_{ij}` the edge weight and
    :math:`w_j` a quadrature weight: the point's area (``normalize="area"``), 1
    (``"mean"``), or no denominator at all (``None``). ``mask`` (False outside the field
    of view) sets :math:`w_j = 0`, so hidden points contribute nothing and the
    normalization uses visible neighbours only. Any rotation (S2) or rigid motion (R3)
    preserves the distances, so the layer is exactly equivariant.

    With ``kernel="basis"`` the per-edge basis values are fixed by the geometry: they are
    precomputed once per graph into K sparse matrices (and their transposes for the
    backward pass); a forward pass is K dense GEMMs and K sparse products per sample. ``kernel="mlp"``
    instead makes a per-edge :math:`C_{in} \times C_{out}` weight from an MLP of the
    distance (slower; for expressivity studies), computed by message passing.

    Args:
        in_channels, out_channels: feature sizes.
        radius: kernel support (radians on S2; units of ``pos`` in R3).
        num_basis: K.
        basis: ``hat`` | ``gaussian`` | ``bessel`` (see :class:`DistanceKernel`).
        kernel: ``basis`` | ``mlp``.
        normalize: ``area`` | ``mean`` | ``None``.
        bias: add a learnable bias.

    Shapes:
        - x: ``[N, C_in]`` (any graph) or ``[B, N, C_in]`` (one graph shared by the batch)
        - edge_index: ``[2, E]``, row 0 the neighbour j and row 1 the centre i
        - edge_weight: ``[E]`` distances
        - node_weight: ``[N]`` areas (``normalize="area"``), mask: ``[N]`` bool
        - output: ``[N, C_out]`` or ``[B, N, C_out]``
    """

    def __init__(self, in_channels: int, out_channels: int, radius: float, num_basis: int = 4,
                 kernel: str = "basis", basis: str = "hat", normalize: str | None = "area",
                 bias: bool = True, hidden: int = 32):
        super().__init__(aggr="add", flow="source_to_target", node_dim=0)
        if kernel not in ("basis", "mlp"):
            raise ValueError(f"kernel must be 'basis' or 'mlp', got {kernel!r}")
        if normalize not in NORMALIZE:
            raise ValueError(f"normalize must be one of {NORMALIZE}, got {normalize!r}")
        self.in_channels, self.out_channels = in_channels, out_channels
        self.radius, self.num_basis, self.kernel_type = float(radius), num_basis, kernel
        self.normalize = normalize
        if kernel == "basis":
            self.kernel = DistanceKernel(num_basis, radius, basis)
            self.weight = nn.Parameter(torch.empty(num_basis * in_channels, out_channels))
        else:
            self.kernel = DistanceKernel(hidden, radius, "mlp")
            self.weight = nn.Parameter(torch.empty(hidden, in_channels * out_channels))
        self.bias = nn.Parameter(torch.empty(out_channels)) if bias else None
        self._plan: tuple | None = None
        self.reset_parameters()

    def reset_parameters(self) -> None:
        super().reset_parameters()
        self.kernel.reset_parameters()
        fan_in = self.weight.shape[0] if self.kernel_type == "basis" else self.in_channels
        bound = (3.0 / fan_in) ** 0.5  # unit-variance output for unit-variance input
        nn.init.uniform_(self.weight, -bound, bound)
        if self.bias is not None:
            nn.init.zeros_(self.bias)

    # -- geometry, computed once per graph -------------------------------------------
    def _edge_coefficients(self, edge_index, edge_weight, num_nodes, node_weight, mask):
        """Per-edge factors phi_k(d_ij) w_j / norm_i ``[E, K]`` (K = hidden for mlp)."""
        j, i = edge_index
        phi = self.kernel(edge_weight)
        w = torch.ones(num_nodes, dtype=phi.dtype, device=phi.device)
        if self.normalize == "area":
            if node_weight is None:
                raise ValueError("normalize='area' needs node_weight (the point areas); pass "
                                 "node_weight=data.area, or use normalize='mean'")
            w = node_weight.to(phi.dtype)
        if mask is not None:
            w = w * mask.to(phi.dtype)
        coef = phi * w[j, None]
        if self.normalize is not None:
            mass = phi.sum(1) if self.kernel_type == "basis" else \
                envelope(edge_weight / self.radius) * (edge_weight < self.radius)
            den = torch.zeros(num_nodes, dtype=phi.dtype, device=phi.device)
            den.index_add_(0, i, mass * w[j])
            coef = coef / den.clamp_min(1e-12)[i, None]
        return coef

    def _plan_for(self, edge_index, edge_weight, num_nodes, node_weight, mask, dtype):
        key = _key(edge_index, edge_weight, node_weight, mask) + (num_nodes, dtype)
        if self._plan is not None and self._plan[0] == key:
            return self._plan[1]
        with torch.no_grad():
            coef = self._edge_coefficients(edge_index, edge_weight, num_nodes, node_weight,
                                           mask).to(dtype)
        j, i = edge_index
        self._plan = (key, plan_tiles(i, j, coef, num_nodes))
        return self._plan[1]

    # -- forward --------------------------------------------------------------------
    def forward(self, x: torch.Tensor, edge_index: torch.Tensor, edge_weight: torch.Tensor,
                node_weight: torch.Tensor | None = None, mask: torch.Tensor | None = None,
                fast: bool = True) -> torch.Tensor:
        if x.shape[-1] != self.in_channels:
            raise ValueError(f"x has {x.shape[-1]} channels, the layer expects {self.in_channels}")
        batched = x.dim() == 3
        N = x.shape[-2]
        if self.kernel_type == "mlp" or not fast:
            out = self._propagate(x, edge_index, edge_weight, N, node_weight, mask)
        else:
            tiles = self._plan_for(edge_index, edge_weight, N, node_weight, mask, x.dtype)
            w = self.weight.view(self.num_basis, self.in_channels, self.out_channels)
            xb = (x if batched else x.unsqueeze(0)).contiguous()
            out = _BasisConv.apply(xb, w.to(x.dtype), tiles)
            out = out if batched else out[0]
        if self.bias is not None:
            out = out + self.bias
        return out

    def _propagate(self, x, edge_index, edge_weight, N, node_weight, mask):
        """Plain per-edge message passing: the reference path (and the mlp kernel)."""
        coef = self._edge_coefficients(edge_index, edge_weight, N, node_weight, mask)
        batched = x.dim() == 3
        xs = x.transpose(0, 1) if batched else x  # [N, (B,) C]
        out = self.propagate(edge_index, x=xs, coef=coef.to(x.dtype), size=(N, N))
        if self.kernel_type == "basis":
            out = out.reshape(*out.shape[:-2], -1) @ self.weight if not batched else \
                torch.einsum("nkbc,kco->nbo", out, self.weight.view(self.num_basis, -1,
                                                                       self.out_channels))
        return out.transpose(0, 1) if batched else out

    def message(self, x_j: torch.Tensor, coef: torch.Tensor) -> torch.Tensor:
        if self.kernel_type == "basis":
            # [E, K, (B,) C]: basis-weighted neighbour features
            return coef.view(*coef.shape, *([1] * (x_j.dim() - 1))) * x_j.unsqueeze(1)
        # mlp: per-edge C_in x C_out weight from the hidden distance features
        W = (coef @ self.weight).view(-1, self.in_channels, self.out_channels)
        if x_j.dim() == 3:
            return torch.einsum("ebc,eco->ebo", x_j, W)
        return torch.einsum("ec,eco->eo", x_j, W)

    def __repr__(self) -> str:
        extra = ", kernel='mlp'" if self.kernel_type == "mlp" else ""
        return (f"{type(self).__name__}({self.in_channels}, {self.out_channels}, "
                f"radius={self.radius:.4g}, num_basis={self.num_basis}, "
                f"basis='{self.kernel.basis}'{extra}, normalize={self.normalize!r})")


class SphericalConv(DistanceConv):
    """:class:`DistanceConv` on S2: ``edge_weight`` holds geodesic distances (radians)
    and ``node_weight`` the cell areas. Exactly SO(3)-equivariant."""


class PointConv(DistanceConv):
    """:class:`DistanceConv` in R3: ``edge_weight`` holds euclidean distances. Invariant
    features under rigid motions (SE(3)); defaults to ``normalize="mean"``."""

    def __init__(self, in_channels: int, out_channels: int, radius: float, num_basis: int = 4,
                 kernel: str = "basis", basis: str = "hat", normalize: str | None = "mean",
                 bias: bool = True, hidden: int = 32):
        super().__init__(in_channels, out_channels, radius, num_basis, kernel, basis, normalize,
                         bias, hidden)
