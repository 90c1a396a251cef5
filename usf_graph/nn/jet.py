"""Rotation-invariant local jet: gradient and Hessian invariants of signals on S2."""

from __future__ import annotations

import hashlib

import numpy as np
import torch
from torch import nn

from ..frontend.cache import GeometryCache
from ..geometry import tangent_towards
from ..graph import nearest_with_ties
from ..sparse import (
    buffer_as,
    csr,
    csr_parts,
    kept,
    padded_operator,
    padded_product,
    quiet_sparse,
    sparse_apply,
    transpose_csr,
)
from ..tracing import field_of, plain_forms
from .batching import from_static, to_static
from .precision import GeometryModule, accumulate_in

# (f, g1, g2, h11, h12, h22): f(q) ~ f + g.u + u^T H u / 2 in p's tangent plane
_TERMS = 6


def tangent_frame(pos: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The tangent frame ``(e1, e2)``, each ``[N, 3]``, in which :func:`jet_operator` writes
    derivatives at unit vectors ``pos [N, 3]``: right-handed with the outward normal
    (``e1 x e2 = p``). The choice is arbitrary; equivariant quantities built from the jet
    are expressed back in 3D with it."""
    ref = torch.zeros_like(pos)
    ref[:, 2] = (pos[:, 2].abs() < 0.9).to(pos.dtype)
    ref[:, 0] = 1 - ref[:, 2]
    e1 = torch.nn.functional.normalize(torch.linalg.cross(ref, pos), dim=1)
    return e1, torch.linalg.cross(pos, e1)


def jet_operator(pos: torch.Tensor, edge_index: torch.Tensor, edge_weight: torch.Tensor,
                 sigma: float, rows: int = 5) -> torch.Tensor:
    r"""Sparse least-squares operator ``[rows N, N]`` giving, at every point p, the gradient
    ``(g1, g2)`` and Hessian ``(h11, h12, h22)`` of a signal in a tangent frame at p
    (``rows=2``: the gradient alone, still from the quadratic fit).

    Each neighbour q (``edge_index`` row 0, centre in row 1, ``edge_weight`` the geodesic
    distance d) gets log-map coordinates :math:`u = d\,\hat t` in that frame, and the fit
    :math:`f(q) \approx f(p) + g^\top u + \tfrac12 u^\top H u` is weighted by
    :math:`e^{-d^2 / 2\sigma^2}`. The frame at p is arbitrary; the invariants that
    :class:`LocalJet` takes from (g, H) do not depend on it. Needs at least 6 neighbours
    per point (a radius of about 3 grid spacings). The frame is right-handed with the
    outward normal (e1 x e2 = p), so the cross product of two gradients is invariant too.
    """
    if rows not in (2, 5):
        raise ValueError(f"rows must be 2 (gradient) or 5 (gradient and Hessian), got {rows}")
    pos = pos.double()
    j, i = edge_index
    n = len(pos)
    e1, e2 = tangent_frame(pos)
    d = edge_weight.double()
    t = tangent_towards(pos[i], pos[j]) * d[:, None]  # log map; 0 at q=p
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
    # rows 1..rows of (A^T W A)^-1 A^T W per edge: one inverse per point, not a solve per edge
    inv = torch.linalg.solve(normal, torch.eye(_TERMS, dtype=pos.dtype).expand(n, -1, -1))
    coef = torch.einsum("erb,eb->er", inv[:, 1:rows + 1][i], w[:, None] * M)  # [E, rows]
    r = torch.cat([i * rows + a for a in range(rows)])
    vals = coef.t().reshape(-1)  # row i * rows + a of edge e: coef[e, a], a-major as r
    return csr(r, j.repeat(rows), vals, (rows * n, n))


# Jet fits in memory only (a level-5 operator is tens of MB, too big to be worth a file);
# every jet of a model, and of every model in the process, on the same graph shares one
_FITS = GeometryCache(directory=None, max_items=32)


def _operator_buffers(pos: torch.Tensor, edge_index: torch.Tensor, edge_weight: torch.Tensor,
                      sigma: float, rows: int) -> dict:
    """The CSR parts (``op_crow``, ``op_col``, ``op_val`` and ``op_t_*`` of the transpose) of
    :func:`jet_operator`, built once per graph and kept in memory (the last 32), keyed by a
    hash of the points, edges and distances themselves, never by where they sit in memory.
    A graph whose points or distances need gradients is fitted afresh, so that the
    gradients reach them."""

    def fit() -> dict:
        op = jet_operator(pos, edge_index, edge_weight, sigma, rows)
        return {f"{name}_{part}": t for name, m in (("op", op), ("op_t", transpose_csr(op)))
                for part, t in zip(("crow", "col", "val"), csr_parts(m))}

    if pos.requires_grad or edge_weight.requires_grad:
        return fit()
    h = hashlib.sha256()
    for t in (pos.double(), edge_index.long(), edge_weight.double()):
        h.update(str(tuple(t.shape)).encode())
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return _FITS.get("jet", {"graph": h.hexdigest(), "sigma": float(sigma), "rows": rows}, fit)


class _Derivatives(GeometryModule):
    """Holds a :func:`jet_operator` (in buffers) and applies it to signals on its graph:
    ``[N, C]``, ``[B, N, C]`` or a PyG batch ``[B N, C]`` with ``batch``."""

    def __init__(self, pos, edge_index, edge_weight, spacing: float, sigma, rows: int):
        super().__init__()
        sigma = float(edge_weight.detach().max()) / 2 if sigma is None else sigma
        self.spacing, self.num_nodes = float(spacing), len(pos)
        for name, t in _operator_buffers(pos, edge_index, edge_weight, sigma, rows).items():
            self.register_buffer(name, t, persistent=False)
        self._rows = rows

    def _operator(self, name: str, dtype, shape) -> torch.Tensor:
        with quiet_sparse():
            return torch.sparse_csr_tensor(getattr(self, f"{name}_crow"),
                                           getattr(self, f"{name}_col"),
                                           buffer_as(self, f"{name}_val", dtype), shape)

    def _derivatives(self, x: torch.Tensor, batch=None) -> tuple[torch.Tensor, torch.Tensor, str]:
        """``x`` -> (``[N, rows, B*C]`` derivatives, ``x`` as ``[B, N, C]``, its form)."""
        xs, form = to_static(x, self.num_nodes, batch, type(self).__name__)
        n, r = self.num_nodes, self._rows
        acc = accumulate_in(xs.dtype)
        flat = xs.permute(1, 0, 2).reshape(n, -1).to(acc)  # [N, B*C]
        if plain_forms(flat):
            y = padded_product(*padded_operator(self, "op", acc, r), flat)
            return y.view(n, r, -1).to(xs.dtype), xs, form
        op = self._operator("op", acc, (r * n, n))
        op_t = self._operator("op_t", acc, (n, r * n))
        return sparse_apply(op, op_t, flat).view(n, r, -1).to(xs.dtype), xs, form

    def extra_repr(self) -> str:
        return f"num_nodes={self.num_nodes}, spacing={self.spacing:.4g}"

    @staticmethod
    def _unflatten(y: torch.Tensor, xs: torch.Tensor, form: str, c: int) -> torch.Tensor:
        """``[N, F, B*C]`` -> the input's form with ``F*C`` channels (F blocks of C)."""
        n, f = y.shape[:2]
        out = y.view(n, f, -1, c).permute(2, 0, 1, 3).reshape(xs.shape[0], n, f * c)
        return from_static(out, form)[0]


class LocalJet(_Derivatives):
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

    Shapes: ``[N, C]``, ``[B, N, C]`` or a PyG batch ``[B N, C]`` with ``batch`` -> the
    same form with ``4 C`` channels (``[f, |g|, lap, det]`` blocks of C).
    """

    def __init__(self, pos, edge_index, edge_weight, spacing: float,
                 sigma: float | None = None):
        super().__init__(pos, edge_index, edge_weight, spacing, sigma, rows=5)

    def forward(self, x: torch.Tensor, batch: torch.Tensor | None = None) -> torch.Tensor:
        """The input and its invariants ``[f, |grad f|, lap f, det Hess f]``, 4 C channels in the
        input's form.
        """
        h = self.spacing
        d, xs, form = self._derivatives(x, batch)
        g1, g2, h11, h12, h22 = d.unbind(1)
        inv = torch.stack([h * torch.sqrt(g1 * g1 + g2 * g2 + 1e-12), h * h * (h11 + h22),
                           h ** 4 * (h11 * h22 - h12 * h12)], 1)  # [N, 3, B*C]
        return torch.cat([x, self._unflatten(inv, xs, form, x.shape[-1])], -1)


class SurfaceJet(_Derivatives):
    r"""The raw jet of every channel: gradient and Hessian in the tangent frame of each
    point (:func:`tangent_frame`, stored as the buffer ``frame [N, 2, 3]``), from the
    quadratic fit of :func:`jet_operator`.

    The components depend on the arbitrary frame, but vectors and tensors rebuilt in 3D
    with it (:math:`\nabla f = g_1 e_1 + g_2 e_2`) rotate exactly with the signal under
    any rotation that maps the grid onto itself: the layer to get directions (a box's
    offset, its axes) out of scalar fields that an isotropic network predicts.

    Shapes: ``[B, N, C]`` -> ``[B, N, C, 5]`` (``g1, g2, h11, h12, h22``, in radians).
    """

    def __init__(self, pos, edge_index, edge_weight, spacing: float,
                 sigma: float | None = None):
        super().__init__(pos, edge_index, edge_weight, spacing, sigma, rows=5)
        e1, e2 = tangent_frame(torch.as_tensor(pos).double())
        self.register_buffer("frame", torch.stack([e1, e2], 1), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Gradient and Hessian ``[B, N, C, 5]`` (``g1, g2, h11, h12, h22``) in each point's tangent
        frame.
        """
        d, xs, _ = self._derivatives(x)  # [N, 5, B*C]
        n, c = self.num_nodes, xs.shape[-1]
        return d.view(n, 5, -1, c).permute(2, 0, 3, 1)


class GradientPairs(_Derivatives):
    r"""Learned pairwise gradient invariants: how strongly, and at what angle, two learned
    features change together.

    .. math::
        \mathbf{a} = \mathbf{x} \mathbf{W}_a,\quad \mathbf{b} = \mathbf{x} \mathbf{W}_b,
        \qquad \mathbf{y}_i = h^2 \big(\langle \nabla a_i, \nabla b_i \rangle,\;
        (\nabla a_i \times \nabla b_i) \cdot \mathbf{n}\big), \quad i = 1..m

    with surface gradients from :func:`jet_operator` (``rows=2``) and :math:`\mathbf{n}`
    the outward normal. A distance-only kernel sees how much a feature varies around a
    point but not in which direction; the dot and cross products of two gradients
    carry their relative angle (a corner, a crossing, two parallel strokes) without a
    reference direction, so they stay exactly SO(3)-invariant (the cross product flips
    sign under reflections only). ``h``, the grid spacing, makes them dimensionless.

    Args:
        pos, edge_index, edge_weight, spacing, sigma: as :class:`LocalJet`;
        in_channels: C; pairs: m.

    Shapes: ``[N, C]``, ``[B, N, C]`` or a PyG batch ``[B N, C]`` with ``batch`` -> the
    same form with ``2 m`` channels (dot products, then cross).
    """

    def __init__(self, pos, edge_index, edge_weight, spacing: float, in_channels: int,
                 pairs: int, sigma: float | None = None):
        super().__init__(pos, edge_index, edge_weight, spacing, sigma, rows=2)
        if in_channels < 1 or pairs < 1:
            raise ValueError(f"in_channels and pairs must be >= 1, got {in_channels}, {pairs}")
        self.in_channels, self.pairs = in_channels, pairs
        self.lin = nn.Linear(in_channels, 2 * pairs, bias=False)  # a constant has no gradient

    def reset_parameters(self) -> None:
        """Re-initializes the projection onto the pairs."""
        self.lin.reset_parameters()

    def forward(self, x: torch.Tensor, batch: torch.Tensor | None = None) -> torch.Tensor:
        """The ``2 m`` invariants of the ``m`` learned gradient pairs, in the input's form."""
        if x.shape[-1] != self.in_channels:
            raise ValueError(f"x has {x.shape[-1]} channels, the layer expects "
                             f"{self.in_channels}")
        m, h2 = self.pairs, self.spacing ** 2
        d, xs, form = self._derivatives(self.lin(x), batch)
        g = d.unflatten(2, (-1, 2, m))  # [N, 2, B, (a|b), m]
        (a1, b1), (a2, b2) = g[:, 0].unbind(-2), g[:, 1].unbind(-2)
        inv = torch.stack([h2 * (a1 * b1 + a2 * b2), h2 * (a1 * b2 - a2 * b1)], 1)
        return self._unflatten(inv.flatten(2), xs, form, m)

    def __repr__(self) -> str:
        return (f"{type(self).__name__}({self.in_channels}, pairs={self.pairs}, "
                f"num_nodes={self.num_nodes}, spacing={self.spacing:.4g})")


def up_frame(frame: torch.Tensor, up: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The tangential part of ``up [B, 3]`` at every point, in the tangent frames
    ``frame [N, 2, 3]``: ``(c, s)``, each ``[N, B]`` (length the sine of the angle to up,
    so it fades to 0 where up is the normal, at the zenith and the nadir)."""
    cs = frame.to(up.dtype) @ up.T  # [N, 2, B]
    return cs[:, 0], cs[:, 1]


class UpJet(SurfaceJet):
    r"""Derivatives of learned fields along and across a given up direction.

    With up's tangential part :math:`\mathbf{t}` at each point (length :math:`\sin\theta`,
    :math:`\theta` the angle to up) and :math:`\mathbf{e} = \mathbf{t} \times \mathbf{n}`,
    for each field :math:`a = \mathbf{x}\mathbf{W}` (``fields`` of them; the identity when
    ``fields`` is ``None``):

    .. math::
        \big(h\,\mathbf{t}^\top\nabla a,\; h\,\mathbf{e}^\top\nabla a,\;
        h^2\,\mathbf{t}^\top\nabla^2 a\,\mathbf{t},\; h^2\,\mathbf{t}^\top\nabla^2 a\,\mathbf{e},\;
        h^2\,\mathbf{e}^\top\nabla^2 a\,\mathbf{e}\big)

    A distance-only kernel cannot tell a vertical edge from a horizontal one; with a
    known or estimated up these five numbers can, like a planar network's oriented
    filters on an upright image. When up rotates with the image (an IMU, or an
    equivariant estimate), they are invariant, so the network stays SO(3)-equivariant.
    Where up is the normal (straight up or down) they fade to 0 with :math:`\sin\theta`.

    Shapes: ``x [B, N, C]``, ``up [B, 3]`` (unit) -> ``[B, N, 5 F]`` (five blocks of F,
    ``F = fields`` or C, in the order above).
    """

    def __init__(self, pos, edge_index, edge_weight, spacing: float, in_channels: int,
                 fields: int | None = None, sigma: float | None = None):
        super().__init__(pos, edge_index, edge_weight, spacing, sigma)
        self.in_channels, self.fields = in_channels, fields
        self.lin = None if fields is None else nn.Linear(in_channels, fields, bias=False)

    def reset_parameters(self) -> None:
        """Re-initializes the learned fields' projection (when ``fields`` is set)."""
        if self.lin is not None:
            self.lin.reset_parameters()

    def forward(self, x: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
        """Gradient and Hessian in up's frame, ``[B, N, 5 F]``, for ``x [B, N, C]`` and unit ``up
        [B, 3]``.
        """
        if x.dim() != 3 or x.shape[-1] != self.in_channels or up.shape != (x.shape[0], 3):
            raise ValueError(f"expected x [B, N, {self.in_channels}] and up [B, 3], got "
                             f"{tuple(x.shape)} and {tuple(up.shape)}")
        h = self.spacing
        d = super().forward(x if self.lin is None else self.lin(x))  # [B, N, F, 5]
        g1, g2, h11, h12, h22 = d.unbind(-1)
        c, s = (v.T[..., None] for v in up_frame(self.frame, up.to(x.dtype)))  # [B, N, 1]
        out = torch.stack([h * (g1 * c + g2 * s), h * (g1 * s - g2 * c),
                           h * h * (c * c * h11 + 2 * c * s * h12 + s * s * h22),
                           h * h * (c * s * (h11 - h22) + (s * s - c * c) * h12),
                           h * h * (s * s * h11 - 2 * c * s * h12 + c * c * h22)], -2)
        return out.flatten(-2)  # [B, N, 5 F], five blocks of F

    def __repr__(self) -> str:
        return (f"{type(self).__name__}({self.in_channels}, fields={self.fields}, "
                f"num_nodes={self.num_nodes}, spacing={self.spacing:.4g})")


class FillHidden(nn.Module):
    """Copies to each hidden point the value of its nearest visible point (the mean of
    the nearest ones when several are equally near, so that symmetric inputs stay
    symmetric).

    Derivatives (the jet) of a signal that drops to 0 outside a lens's field of view see a
    false edge along its border; extending the image by its nearest visible value removes
    it. The index is built once per mask (a k-d tree query) and memoized."""

    def __init__(self, pos: torch.Tensor):
        super().__init__()
        self.pos = pos.double().numpy()
        self._index: dict[bytes, tuple] = {}

    def _build(self, m: np.ndarray) -> tuple:
        vis, hid = np.flatnonzero(m), np.flatnonzero(~m)
        d, j = nearest_with_ties(self.pos[vis], self.pos[hid], 1)
        w = np.isfinite(d).astype(np.float64)
        return (torch.as_tensor(hid), torch.as_tensor(vis[j]),
                torch.as_tensor(w / w.sum(1, keepdims=True)))

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        """``x [B, N, C]`` with every point ``mask [N]`` hides set to its nearest visible value
        (``x`` itself without a mask).
        """
        if mask is None:
            return x
        m = field_of(mask)
        key = np.packbits(m).tobytes()
        if key not in self._index:
            if len(self._index) > 16:
                self._index.clear()
            with kept():  # served to later calls in any mode
                self._index[key] = self._build(m)
        hid, src, w = (t.to(x.device) for t in self._index[key])
        out = x.clone()
        out[:, hid] = (x[:, src] * w.to(x.dtype)[..., None]).sum(-2)
        return out
