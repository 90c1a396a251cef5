"""Pooling on grids: coarsening clusters, unpooling, global pooling; all mask-aware."""

from __future__ import annotations

import math

import torch
from torch import nn

from ..graph import euclidean_radius, geodesic_radius, nearest_with_ties
from ..sparse import (
    buffer_as,
    csr,
    csr_parts,
    padded_operator,
    padded_product,
    quiet_sparse,
    row_pointers,
)
from ..tracing import plain_forms
from .batching import check_per_point, from_static, mask_static, pooled_batch, to_static
from .precision import GeometryModule, accumulate_in


class GridPool(GeometryModule):
    r"""Pools a fine grid onto its coarsening (``cluster`` from ``grid.coarsen()``).

    ``mode="mean"``: :math:`y_c = \sum_{j \in c} a_j m_j x_j / \sum_{j \in c} a_j m_j`
    (area-weighted, visible points only); ``mode="max"``: maximum over visible points.
    A coarse point with no visible fine point gets 0 and is masked out.
    Uses torch-scatter's ``segment_csr`` on the clusters, sorted once at construction.

    Shapes:
        - x: ``[N, C]``, ``[B, N, C]``, or a PyG batch ``[B N, C]`` with ``batch [B N]``
        - mask: ``[N]``, ``[B, N]`` or ``[B N]`` (optional)
        - output: ``(y, coarse mask)`` in the input's form (``[M, C]``, ``[B, M, C]``;
          mask ``[M]``, or ``[B, M]`` for per-sample masks), plus the coarse ``batch
          [B M]`` for a PyG batch: ``(y [B M, C], mask [B M], batch [B M])``
    """

    def __init__(self, cluster: torch.Tensor, num_coarse: int | None = None, mode: str = "max",
                 area: torch.Tensor | None = None):
        super().__init__()
        if mode not in ("max", "mean"):
            raise ValueError(f"mode must be 'max' or 'mean', got {mode!r}")
        cluster = torch.as_tensor(cluster, dtype=torch.long)
        self.mode = mode
        self.num_coarse = int(num_coarse if num_coarse is not None else cluster.max() + 1)
        perm = torch.argsort(cluster, stable=True)
        counts = torch.bincount(cluster, minlength=self.num_coarse)
        self.register_buffer("cluster", cluster, persistent=False)
        self.register_buffer("perm", perm, persistent=False)
        self.register_buffer("indptr", row_pointers(counts), persistent=False)
        self.register_buffer("area", None if area is None else torch.as_tensor(area),
                             persistent=False)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None,
                batch: torch.Tensor | None = None):
        """``(y, coarse mask)`` on the coarse grid (and the coarse ``batch`` for a PyG batch); see
        Shapes.
        """
        from torch_scatter import segment_csr

        xs, form = to_static(x, len(self.cluster), batch, type(self).__name__)
        ms = mask_static(mask, xs, form)
        xf = xs.transpose(0, 1)  # [N, B, C]: segments along dim 0
        m = torch.ones(xf.shape[:2], dtype=xf.dtype, device=xf.device) if ms is None \
            else ms.t().to(xf.dtype)
        m_c = segment_csr(m[self.perm], self.indptr, reduce="max") > 0  # [M, B]
        if self.mode == "mean":
            w = m * (self.area.to(xf.dtype)[:, None] if self.area is not None else 1.0)
            num = segment_csr((xf * w[..., None])[self.perm], self.indptr, reduce="sum")
            den = segment_csr(w[self.perm], self.indptr, reduce="sum")
            out = num / den.clamp_min(1e-30)[..., None]
        else:
            src = xf if ms is None else xf.masked_fill(~ms.t()[..., None], float("-inf"))
            out = segment_csr(src[self.perm], self.indptr, reduce="max")
            out = out.masked_fill(~m_c[..., None], 0.0)
        return _pooled(out.transpose(0, 1), m_c.t(), form, mask)

    def extra_repr(self) -> str:
        return f"{len(self.cluster)} -> {self.num_coarse}, mode='{self.mode}'"


def _pooled(y, m, form, given):
    """A pool's result in its input's form; a PyG batch also gets the coarse ``batch``."""
    out, mask = from_static(y, form, m, given)
    if form == "pyg":
        return out, mask, pooled_batch(y.shape[0], y.shape[1], y.device)
    return out, mask


class GaussianPool(GeometryModule):
    r"""Anti-aliased pooling of a fine grid onto a coarser point set.

    Each coarse point :math:`c` takes the area-weighted Gaussian average of the visible fine
    points within :math:`3\sigma`:

    .. math::
        y_c = \frac{\sum_j a_j m_j e^{-d_{cj}^2 / 2\sigma^2} x_j}
                   {\sum_j a_j m_j e^{-d_{cj}^2 / 2\sigma^2}}

    Plain subsampling (:class:`GridPool`) keeps frequencies the coarse grid cannot hold, and
    they alias differently at every placement of the signal, which breaks rotation
    invariance off the grid's own symmetries. Blurring first, as in anti-aliased CNNs
    (Zhang 2019), keeps pooled features nearly equivariant to any rotation. A Gaussian of
    geodesic distance is isotropic, so the layer commutes exactly with rotations that map
    both point sets onto themselves. ``sigma`` defaults to 0.5 coarse spacings.

    Shapes: as :class:`GridPool` (``x``, ``mask``, ``batch`` in any of the three forms).
    """

    def __init__(self, fine_pos: torch.Tensor, coarse_pos: torch.Tensor, sigma: float,
                 area: torch.Tensor | None = None):
        super().__init__()
        if not sigma > 0:
            raise ValueError(f"sigma must be > 0 radians, got {sigma}")
        fine, coarse = torch.as_tensor(fine_pos).double(), torch.as_tensor(coarse_pos).double()
        (j, c), d = geodesic_radius(fine, coarse, min(3 * sigma, math.pi))
        w = torch.exp(-0.5 * (d / sigma) ** 2)
        if area is not None:
            w = w * torch.as_tensor(area, dtype=w.dtype)[j]
        self.sigma, self.num_coarse, self.num_fine = float(sigma), len(coarse), len(fine)
        P = csr(c, j, w, (len(coarse), len(fine)))
        # dense buffers (not a sparse one) so .to(), DDP and state handling stay plain
        for part, t in zip(("crow", "col", "val"), csr_parts(P)):
            self.register_buffer(part, t, persistent=False)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None,
                batch: torch.Tensor | None = None):
        """``(y, coarse mask)`` on the coarse grid (and the coarse ``batch`` for a PyG batch); see
        Shapes.
        """
        xs, form = to_static(x, self.num_fine, batch, type(self).__name__)
        ms = mask_static(mask, xs, form)
        B, N, C = xs.shape
        acc = accumulate_in(xs.dtype)
        xf = xs.transpose(0, 1).to(acc)  # [N, B, C]
        m = torch.ones(N, B, dtype=acc, device=xs.device) if ms is None else ms.t().to(acc)
        if plain_forms(xf):
            op = padded_operator(self, "", acc)
            den = padded_product(*op, m)  # [M, B]
            num = padded_product(*op, xf * m[..., None])
        else:
            with quiet_sparse():
                P = torch.sparse_csr_tensor(self.crow, self.col, buffer_as(self, "val", acc),
                                            (self.num_coarse, self.num_fine))
                den = P @ m
                num = (P @ (xf * m[..., None]).reshape(N, B * C)).view(-1, B, C)
        y = (num / den.clamp_min(1e-30)[..., None]).to(xs.dtype)
        return _pooled(y.transpose(0, 1), (den > 0).t(), form, mask)

    def extra_repr(self) -> str:
        return f"{self.num_fine} -> {self.num_coarse}, sigma={self.sigma:.4g}"


class GridUnpool(GeometryModule):
    """Coarse -> fine: ``nearest`` copies the point's cluster value; ``linear`` blends the
    three nearest coarse points by inverse squared distance (needs the positions), with any
    point tied with the third (:func:`~usf_graph.graph.nearest_with_ties`) taking part too,
    so that the blend commutes with the grid's symmetries.

    Shapes: ``[M, C]``, ``[B, M, C]``, or a PyG batch ``[B M, C]`` with ``batch`` ->
    the same form on the fine grid (a PyG batch returns ``(y [B N, C], batch [B N])``).
    """

    def __init__(self, cluster: torch.Tensor, mode: str = "nearest", fine_pos=None,
                 coarse_pos=None):
        super().__init__()
        if mode not in ("nearest", "linear"):
            raise ValueError(f"mode must be 'nearest' or 'linear', got {mode!r}")
        self.mode = mode
        cluster = torch.as_tensor(cluster, dtype=torch.long)
        if mode == "nearest":
            self.num_coarse = int(cluster.max()) + 1
            idx = cluster[:, None]
            w = torch.ones(idx.shape, dtype=torch.float64)
        else:
            if fine_pos is None or coarse_pos is None:
                raise ValueError("mode='linear' needs fine_pos and coarse_pos")
            self.num_coarse = len(coarse_pos)
            # on a symmetric grid the third place is often a tie (72 of icosahedral:2's 162
            # points): every tied point takes part, so the blend commutes with the symmetries
            d, idx = nearest_with_ties(coarse_pos, fine_pos, 3)
            d, idx = torch.as_tensor(d), torch.as_tensor(idx, dtype=torch.long)
            w = torch.where(torch.isfinite(d), 1.0 / d.clamp_min(1e-12) ** 2, 0.0)
            w = w / w.sum(1, keepdim=True)
            # a fine point on a coarse point takes its value exactly
            exact = d[:, 0] < 1e-12
            w[exact] = 0.0
            w[exact, 0] = 1.0
        self.register_buffer("idx", idx, persistent=False)
        self.register_buffer("w", w, persistent=False)

    def forward(self, x: torch.Tensor, batch: torch.Tensor | None = None):
        """``x`` on the fine grid (with the fine ``batch`` for a PyG batch); see Shapes."""
        xs, form = to_static(x, self.num_coarse, batch, type(self).__name__)
        g = xs[:, self.idx, :]  # [B, N, P, C]
        y, _ = from_static((g * self.w.to(xs.dtype)[..., None]).sum(-2), form)
        if form == "pyg":
            return y, pooled_batch(xs.shape[0], self.idx.shape[0], y.device)
        return y

    def extra_repr(self) -> str:
        return f"{self.num_coarse} -> {self.idx.shape[0]} points, mode='{self.mode}'"


def _readout_weights(x, area, mask, batch):
    """Per-point weights (area times visibility) broadcastable to ``x[..., :1]``."""
    check_per_point("area", area, x.shape[-2])
    check_per_point("mask", mask, x.shape[-2], 1 if batch is not None else x.dim() - 1)
    w = torch.ones(x.shape[-2], dtype=x.dtype, device=x.device) if area is None \
        else area.to(x.dtype)
    if mask is not None:
        w = w * mask.to(x.dtype)
    return w[..., None]


def _num_graphs(batch: torch.Tensor, x: torch.Tensor) -> int:
    if x.dim() != 2 or batch.shape != (x.shape[0],):
        raise ValueError(f"with batch, x must be [sum N_i, C] and batch [sum N_i]; got "
                         f"{tuple(x.shape)} and {tuple(batch.shape)}")
    return int(batch.max()) + 1 if batch.numel() else 0


def global_mean_pool_area(x: torch.Tensor, area: torch.Tensor | None = None,
                          mask: torch.Tensor | None = None,
                          batch: torch.Tensor | None = None) -> torch.Tensor:
    """Area-weighted mean over visible points, per graph: ``[N, C] -> [C]``,
    ``[B, N, C] -> [B, C]`` (mask ``[N]`` or ``[B, N]``), or a PyG batch ``[sum N_i, C]``
    with ``batch`` (``area`` and ``mask`` per point) -> ``[num_graphs, C]``, like
    :func:`torch_geometric.nn.global_mean_pool`."""
    w = _readout_weights(x, area, mask, batch)
    if batch is None:
        return (x * w).sum(-2) / w.sum(-2).clamp_min(1e-30)
    G = _num_graphs(batch, x)
    num = x.new_zeros(G, x.shape[-1]).index_add_(0, batch, x * w)
    den = x.new_zeros(G, 1).index_add_(0, batch, w)
    return num / den.clamp_min(1e-30)


def global_max_pool_masked(x: torch.Tensor, mask: torch.Tensor | None = None,
                           batch: torch.Tensor | None = None) -> torch.Tensor:
    """Maximum over visible points, per graph: ``[(B,) N, C] -> [(B,) C]`` or a PyG batch
    with ``batch`` -> ``[num_graphs, C]``. A graph with no visible point gets 0."""
    check_per_point("mask", mask, x.shape[-2], 1 if batch is not None else x.dim() - 1)
    if mask is not None:
        x = x.masked_fill(~mask.bool()[..., None], float("-inf"))
    if batch is None:
        out = x.amax(-2)
    else:
        G = _num_graphs(batch, x)
        out = x.new_full((G, x.shape[-1]), float("-inf")).scatter_reduce(
            0, batch[:, None].expand_as(x), x, "amax")
    return out.masked_fill(torch.isneginf(out), 0.0)


def farthest_point_sampling(pos: torch.Tensor, batch: torch.Tensor | None = None,
                            ratio: float = 0.25) -> torch.Tensor:
    """Indices of ``ratio`` of the points of each cloud, by ``torch_cluster.fps``.

    The start is canonical: the point farthest from its cloud's centroid. The samples are
    then the same set under any rigid motion and any permutation of the points, which a
    fixed or random start index would not give. ``batch`` must be sorted.
    """
    import torch_cluster
    from torch_scatter import scatter_max, scatter_mean

    if not 0 < ratio <= 1:
        raise ValueError(f"ratio must be in (0, 1], got {ratio}")
    batch = torch.zeros(len(pos), dtype=torch.long, device=pos.device) if batch is None else batch
    cen = scatter_mean(pos, batch, dim=0)
    far = scatter_max((pos - cen[batch]).norm(dim=-1), batch)[1]  # canonical start per cloud
    first = torch.searchsorted(batch, torch.arange(len(far), device=pos.device))
    perm = torch.arange(len(pos), device=pos.device)
    perm[first], perm[far] = far, first
    idx = torch_cluster.fps(pos[perm], batch, ratio=ratio, random_start=False)
    return perm[idx]


class FPSPool(nn.Module):
    r"""Farthest point sampling plus radius assignment, for point clouds in R3.

    Each sampled centre :math:`c` takes the maximum of the features of all points within
    ``radius`` of it, :math:`y_c = \max_{|p_j - p_c| \le r} x_j`. Both the sampling
    (:func:`farthest_point_sampling`) and the assignment depend only on distances, so the
    pooled features are invariant to rigid motions (a voxel grid would not be).

    Shapes: ``x [N, C]``, ``pos [N, 3]``, ``batch [N]`` ->
    ``(x [M, C], pos [M, 3], batch [M], idx [M])``.
    """

    def __init__(self, ratio: float = 0.25, radius: float = 0.5):
        super().__init__()
        if not 0 < ratio <= 1 or not radius > 0:
            raise ValueError(f"FPSPool needs ratio in (0, 1] and radius > 0, got {ratio}, {radius}")
        self.ratio, self.radius = float(ratio), float(radius)

    def forward(self, x, pos, batch=None):
        """``(x [M, C], pos [M, 3], batch [M], idx [M])`` at the sampled centres."""
        from torch_scatter import scatter_max

        batch = torch.zeros(len(pos), dtype=torch.long, device=pos.device) if batch is None else batch
        idx = farthest_point_sampling(pos, batch, self.ratio)
        ei, _ = euclidean_radius(pos, pos[idx], self.radius, batch, batch[idx])
        out = scatter_max(x[ei[0]], ei[1], dim=0, dim_size=len(idx))[0]
        return out, pos[idx], batch[idx], idx

    def extra_repr(self) -> str:
        return f"ratio={self.ratio:g}, radius={self.radius:g}"
