"""Pooling on grids: coarsening clusters, unpooling, global pooling; all mask-aware."""

from __future__ import annotations

import math

import torch
from scipy.spatial import cKDTree
from torch import nn

from .sparse import csr, quiet_sparse


def _node_first(x: torch.Tensor):
    """[N, C] or [B, N, C] -> ([N, B*C], restore)."""
    if x.dim() == 2:
        return x, lambda y: y
    B, N, C = x.shape
    return x.transpose(0, 1).reshape(N, B * C), lambda y: y.reshape(-1, B, C).transpose(0, 1)


class GridPool(nn.Module):
    r"""Pools a fine grid onto its coarsening (``cluster`` from ``grid.coarsen()``).

    ``mode="mean"``: :math:`y_c = \sum_{j \in c} a_j m_j x_j / \sum_{j \in c} a_j m_j`
    (area-weighted, visible points only); ``mode="max"``: maximum over visible points.
    A coarse point with no visible fine point gets 0 and is masked out.
    Uses torch-scatter's ``segment_csr`` on the clusters, sorted once at construction.

    Shapes:
        - x: ``[N, C]`` or ``[B, N, C]``, mask: ``[N]`` (optional)
        - output: ``([M, C] or [B, M, C], coarse mask [M])``
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
        self.register_buffer("indptr", torch.cat([counts.new_zeros(1), counts.cumsum(0)]),
                             persistent=False)
        self.register_buffer("area", None if area is None else torch.as_tensor(area),
                             persistent=False)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None):
        from torch_scatter import segment_csr

        xf, restore = _node_first(x)
        m = torch.ones(xf.shape[0], dtype=xf.dtype, device=xf.device) if mask is None \
            else mask.to(xf.dtype)
        m_c = segment_csr(m[self.perm], self.indptr, reduce="max") > 0
        if self.mode == "mean":
            w = m * (self.area.to(xf.dtype) if self.area is not None else 1.0)
            num = segment_csr((xf * w[:, None])[self.perm], self.indptr, reduce="sum")
            den = segment_csr(w[self.perm], self.indptr, reduce="sum")
            out = num / den.clamp_min(1e-30)[:, None]
        else:
            src = xf if mask is None else xf.masked_fill(~mask.bool()[:, None], float("-inf"))
            out = segment_csr(src[self.perm], self.indptr, reduce="max")
            out = out.masked_fill(~m_c[:, None], 0.0)
        return restore(out), m_c

    def extra_repr(self) -> str:
        return f"{len(self.cluster)} -> {self.num_coarse}, mode='{self.mode}'"


class GaussianPool(nn.Module):
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

    Shapes:
        - x: ``[N, C]`` or ``[B, N, C]``, mask: ``[N]`` (optional)
        - output: ``([M, C] or [B, M, C], coarse mask [M])``
    """

    def __init__(self, fine_pos: torch.Tensor, coarse_pos: torch.Tensor, sigma: float,
                 area: torch.Tensor | None = None):
        super().__init__()
        from .graph import geodesic_radius

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
        self.register_buffer("crow", P.crow_indices(), persistent=False)
        self.register_buffer("col", P.col_indices(), persistent=False)
        self.register_buffer("val", P.values(), persistent=False)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None):
        xf, restore = _node_first(x)
        m = torch.ones(xf.shape[0], 1, dtype=xf.dtype, device=xf.device) if mask is None \
            else mask.to(xf.dtype)[:, None]
        with quiet_sparse():
            P = torch.sparse_csr_tensor(self.crow, self.col, self.val.to(xf.dtype),
                                        (self.num_coarse, self.num_fine))
            den = (P @ m)[:, 0]
            num = P @ (xf if mask is None else xf * m)
        m_c = den > 0
        return restore(num / den.clamp_min(1e-30)[:, None]), m_c

    def extra_repr(self) -> str:
        return f"{self.num_fine} -> {self.num_coarse}, sigma={self.sigma:.4g}"


class GridUnpool(nn.Module):
    """Coarse -> fine: ``nearest`` copies the point's cluster value; ``linear`` blends the
    three nearest coarse points by inverse squared distance (needs the positions).

    Shapes: ``[M, C]`` or ``[B, M, C]`` -> ``[N, C]`` or ``[B, N, C]``.
    """

    def __init__(self, cluster: torch.Tensor, mode: str = "nearest", fine_pos=None,
                 coarse_pos=None):
        super().__init__()
        if mode not in ("nearest", "linear"):
            raise ValueError(f"mode must be 'nearest' or 'linear', got {mode!r}")
        self.mode = mode
        if mode == "nearest":
            idx = torch.as_tensor(cluster, dtype=torch.long)[:, None]
            w = torch.ones(idx.shape, dtype=torch.float64)
        else:
            if fine_pos is None or coarse_pos is None:
                raise ValueError("mode='linear' needs fine_pos and coarse_pos")
            d, j = cKDTree(torch.as_tensor(coarse_pos).numpy()).query(
                torch.as_tensor(fine_pos).numpy(), k=3)
            w = 1.0 / torch.as_tensor(d).clamp_min(1e-12) ** 2
            w = w / w.sum(1, keepdim=True)
            # a fine point on a coarse point takes its value exactly
            exact = torch.as_tensor(d[:, 0] < 1e-12)
            w[exact] = torch.tensor([1.0, 0.0, 0.0], dtype=w.dtype)
            idx = torch.as_tensor(j, dtype=torch.long)
        self.register_buffer("idx", idx, persistent=False)
        self.register_buffer("w", w, persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        g = x[..., self.idx, :]  # [..., N, P, C]
        return (g * self.w.to(x.dtype)[..., None]).sum(-2)

    def extra_repr(self) -> str:
        return f"{self.idx.shape[0]} points, mode='{self.mode}'"


def global_mean_pool_area(x: torch.Tensor, area: torch.Tensor | None = None,
                          mask: torch.Tensor | None = None) -> torch.Tensor:
    """Area-weighted mean over visible points: ``[(B,) N, C] -> [(B,) C]``."""
    w = torch.ones(x.shape[-2], dtype=x.dtype, device=x.device) if area is None else area.to(x.dtype)
    if mask is not None:
        w = w * mask.to(x.dtype)
    return (x * w[:, None]).sum(-2) / w.sum().clamp_min(1e-30)


def global_max_pool_masked(x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Maximum over visible points: ``[(B,) N, C] -> [(B,) C]``."""
    if mask is not None:
        x = x.masked_fill(~mask.bool()[:, None], float("-inf"))
    return x.amax(-2)


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
        self.ratio, self.radius = float(ratio), float(radius)

    def forward(self, x, pos, batch=None):
        from torch_scatter import scatter_max

        from .graph import euclidean_radius

        batch = torch.zeros(len(pos), dtype=torch.long, device=pos.device) if batch is None else batch
        idx = farthest_point_sampling(pos, batch, self.ratio)
        ei, _ = euclidean_radius(pos, pos[idx], self.radius, batch, batch[idx])
        out = scatter_max(x[ei[0]], ei[1], dim=0, dim_size=len(idx))[0]
        return out, pos[idx], batch[idx], idx

    def extra_repr(self) -> str:
        return f"ratio={self.ratio:g}, radius={self.radius:g}"
