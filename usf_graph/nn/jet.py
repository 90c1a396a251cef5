"""Rotation-invariant local jet: gradient and Hessian invariants of signals on S2."""

from __future__ import annotations

import torch
from torch import nn

from .sparse import quiet_sparse

# (f, g1, g2, h11, h12, h22): f(q) ~ f + g.u + u^T H u / 2 in p's tangent plane
_TERMS = 6


def jet_operator(pos: torch.Tensor, edge_index: torch.Tensor, edge_weight: torch.Tensor,
                 sigma: float) -> torch.Tensor:
    r"""Sparse least-squares operator ``[5 N, N]`` giving, at every point p, the gradient
    ``(g1, g2)`` and Hessian ``(h11, h12, h22)`` of a signal in a tangent frame at p.

    Each neighbour q (``edge_index`` row 0, centre in row 1, ``edge_weight`` the geodesic
    distance d) gets log-map coordinates :math:`u = d\,\hat t` in that frame, and the fit
    :math:`f(q) \approx f(p) + g^\top u + \tfrac12 u^\top H u` is weighted by
    :math:`e^{-d^2 / 2\sigma^2}`. The frame at p is arbitrary; the invariants that
    :class:`LocalJet` takes from (g, H) do not depend on it. Needs at least 6 neighbours
    per point (a radius of about 3 grid spacings).
    """
    pos = pos.double()
    j, i = edge_index
    n = len(pos)
    ref = torch.zeros_like(pos)
    ref[:, 2] = (pos[:, 2].abs() < 0.9).double()
    ref[:, 0] = 1 - ref[:, 2]
    e1 = torch.nn.functional.normalize(torch.linalg.cross(ref, pos), dim=1)
    e2 = torch.linalg.cross(pos, e1)
    d = edge_weight.double()
    t = pos[j] - (pos[j] * pos[i]).sum(1, keepdim=True) * pos[i]
    t = t / t.norm(dim=1, keepdim=True).clamp_min(1e-300) * d[:, None]  # log map; 0 at q=p
    u1, u2 = (t * e1[i]).sum(1), (t * e2[i]).sum(1)
    w = torch.exp(-0.5 * (d / sigma) ** 2)
    M = torch.stack([torch.ones_like(u1), u1, u2, 0.5 * u1 * u1, u1 * u2, 0.5 * u2 * u2], 1)
    normal = torch.zeros(n, _TERMS, _TERMS, dtype=pos.dtype).index_add_(
        0, i, w[:, None, None] * M[:, :, None] * M[:, None, :])
    counts = torch.bincount(i, minlength=n)
    cond = torch.linalg.cond(normal)
    if (counts < _TERMS).any() or not torch.isfinite(cond).all() or cond.max() > 1e12:
        raise ValueError(f"the local jet needs >= {_TERMS} well-spread neighbours per point "
                         f"(fewest: {int(counts.min())}); use a larger radius")
    coef = torch.linalg.solve(normal[i], w[:, None] * M)  # [E, 6] rows of (A^T W A)^-1 A^T W
    rows = torch.cat([i * 5 + a for a in range(5)])
    vals = torch.cat([coef[:, a + 1] for a in range(5)])
    with quiet_sparse():
        return torch.sparse_coo_tensor(torch.stack([rows, j.repeat(5)]), vals,
                                       (5 * n, n)).coalesce().to_sparse_csr()


class LocalJet(nn.Module):
    r"""Per channel, the signal and three rotation-invariant differential invariants:

    .. math::
        \big(f,\; h\,\lVert\nabla f\rVert,\; h^2\,\Delta f,\; h^4 \det \nabla^2 f\big)

    from a local quadratic fit (:func:`jet_operator`), made dimensionless with the grid
    spacing ``h``. A distance-only kernel cannot tell a stroke's edge from its centre
    line or a bend from a straight piece; these invariants can, and they stay exactly
    SO(3)-invariant because they do not depend on the tangent frame.

    Args:
        pos: ``[N, 3]`` points; edge_index/edge_weight: their geodesic radius graph;
        spacing: h; sigma: the fit's Gaussian width (default: the radius / 2).

    Shapes: ``[N, C]`` or ``[B, N, C]`` -> ``[..., N, 4 C]`` (``[f, |g|, lap, det]``
    blocks of C).
    """

    def __init__(self, pos, edge_index, edge_weight, spacing: float,
                 sigma: float | None = None):
        super().__init__()
        sigma = float(edge_weight.max()) / 2 if sigma is None else sigma
        self.spacing, self.num_nodes = float(spacing), len(pos)
        self._op = jet_operator(pos, edge_index, edge_weight, sigma)
        self._cast: dict = {}

    def _operator(self, like: torch.Tensor) -> torch.Tensor:
        key = (like.dtype, like.device)
        if key not in self._cast:
            self._cast[key] = self._op.to(device=like.device, dtype=like.dtype)
        return self._cast[key]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[-2] != self.num_nodes:
            raise ValueError(f"x has {x.shape[-2]} points, the jet was built for "
                             f"{self.num_nodes}")
        lead, (n, c) = x.shape[:-2], x.shape[-2:]
        flat = x.reshape(-1, n, c).permute(1, 0, 2).reshape(n, -1)  # [N, B*C]
        with quiet_sparse():
            d = (self._operator(x) @ flat).view(n, 5, -1)
        h = self.spacing
        g1, g2, h11, h12, h22 = d.unbind(1)
        inv = torch.stack([h * torch.sqrt(g1 * g1 + g2 * g2 + 1e-12), h * h * (h11 + h22),
                           h ** 4 * (h11 * h22 - h12 * h12)], 1)  # [N, 3, B*C]
        inv = inv.view(n, 3, -1, c).permute(2, 0, 1, 3).reshape(*lead, n, 3 * c)
        return torch.cat([x, inv], -1)

    def extra_repr(self) -> str:
        return f"num_nodes={self.num_nodes}, spacing={self.spacing:.4g}"
