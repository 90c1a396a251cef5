"""SphericalConv / PointConv: convolution with a kernel of distance only."""

from __future__ import annotations

import torch
from torch import nn
from torch_geometric.nn import MessagePassing

from ..geometry import tangent_towards
from .aggregate import EdgePlan, basis_aggregate
from .kernel import DistanceKernel, envelope

NORMALIZE = ("area", "mean", None)


class DistanceConv(MessagePassing):
    r"""Convolution whose kernel depends only on the distance between points.

    .. math::
        \mathbf{y}_i = \sum_{k=1}^{K} \mathbf{W}_k^\top
        \frac{\sum_{j \in \mathcal{N}(i)} \phi_k(d_{ij})\, w_j\, \mathbf{x}_j}
             {\sum_{j \in \mathcal{N}(i)} w_j\, \phi(d_{ij})} + \mathbf{b}

    with :math:`\phi_k` from :class:`DistanceKernel`, :math:`\phi = \sum_k \phi_k` for the
    positive bases (``hat``, ``gaussian``) and the kernel's smooth envelope for those that
    change sign (``bessel``, ``mlp``, whose sum could vanish), :math:`d_{ij}` the edge weight and
    :math:`w_j` a quadrature weight: ``node_weight`` (the point's area) with
    ``normalize="area"``, 1 with ``"mean"`` or when no ``node_weight`` is given (exact on
    equal-area grids such as HEALPix), and no denominator at all with ``None``. ``mask``
    (False outside the field of view) sets :math:`w_j = 0`, so hidden points contribute
    nothing and the normalization uses visible neighbours only. Any rotation (S2) or rigid
    motion (R3) preserves the distances, so the layer is exactly equivariant.

    **Two ways to give the graph.**

    * PyG's form: ``conv(x, edge_index, edge_weight[, node_weight, mask])``, any graph on
      every call (a batch of different graphs as ``[sum N_i, C]``). The per-edge
      coefficients are computed in that call, with autograd. The sparse structure
      (:class:`~usf_graph.nn.aggregate.EdgePlan`) of the last call's graph is kept and
      reused while ``edge_index`` stays equal by value (a loader's batches of one grid),
      checked against the layer's own copy; another graph replaces it.
    * The static-graph fast path: ``conv.bind(edge_index, edge_weight, node_weight, mask)``
      once (one camera and grid), then ``conv(x)`` with ``x [B, N, C]``. The structure
      and, while nothing needs their gradient, the coefficients live in non-persistent
      buffers that follow ``.to()``; a ``mask=`` passed to the call replaces the bound one
      for that call. Bind again to change the graph; in-place edits of the bound tensors
      are noticed through their version counters. ``reset_parameters`` clears the cached
      coefficients. Geometry is never matched to inputs by memory address.

    With ``kernel="basis"`` a forward pass is K sparse products and K dense GEMMs per
    sample on the CPU, and one of each for the whole batch on a GPU
    (:func:`~usf_graph.nn.aggregate.basis_aggregate`); gradients reach ``x``, the
    weights and the coefficients, hence ``edge_weight``, ``node_weight`` and a learnable
    basis. ``kernel="mlp"`` makes a per-edge :math:`C_{in} \times C_{out}` weight from an MLP
    of the distance (slower; for expressivity studies), by message passing, as does
    ``fast=False`` (the plain per-edge reference).

    **Initialization.** Entries of :math:`\mathbf{W}` are uniform with variance
    :math:`1/(K C_{in})` and the bias is 0. For any fixed input, the output's second
    moment, averaged over initializations, is the mean second moment of the
    :math:`K C_{in}` aggregated features :math:`\mathbf{u}_{ik} = \sum_j a_{ijk}
    \mathbf{x}_j` (fan-in rule with gain 1). A signal that is constant over each
    neighbourhood keeps its scale up to :math:`\sum_k m_k^2 / K \in [1/K^2, 1/K]`
    (:math:`m_k` the share of basis k); white noise shrinks further, by the averaging.
    Follow the layer with a normalization (:class:`MaskedBatchNorm`).

    Args:
        in_channels, out_channels: feature sizes.
        radius: kernel support (radians on S2; units of ``pos`` in R3).
        num_basis: K.
        kernel: ``basis`` | ``mlp``.
        basis: ``hat`` | ``gaussian`` | ``bessel`` | ``mlp`` (learnable; see
            :class:`DistanceKernel`).
        normalize: ``area`` | ``mean`` | ``None``.
        bias: add a learnable bias.

    Shapes:
        - x: ``[N, C_in]`` (any graph) or ``[B, N, C_in]`` (one graph shared by the batch)
        - edge_index: ``[2, E]``, row 0 the neighbour j and row 1 the centre i
        - edge_weight: ``[E]`` distances, or ``[E, 1]`` (a :class:`SphericalImage`'s
          ``edge_attr``, PyG's ``Distance`` layout)
        - node_weight: ``[N]`` areas (optional), mask: ``[N]`` bool (optional)
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
        self.plan: EdgePlan | None = None
        for name in ("bound_edge_index", "bound_edge_weight", "bound_node_weight",
                     "bound_mask", "_coef"):
            self.register_buffer(name, None, persistent=False)
        self._coef_key = None
        self._plans: dict = {}  # PyG form: the last graph's plan (a dict: not a submodule)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        super().reset_parameters()
        self.kernel.reset_parameters()
        bound = (3.0 / self.weight.shape[0]) ** 0.5  # variance 1 / fan-in (K C_in; hidden)
        nn.init.uniform_(self.weight, -bound, bound)
        if self.bias is not None:
            nn.init.zeros_(self.bias)
        self._coef, self._coef_key = None, None

    # -- geometry --------------------------------------------------------------------
    def bind(self, edge_index: torch.Tensor, edge_weight: torch.Tensor,
             node_weight: torch.Tensor | None = None, mask: torch.Tensor | None = None,
             num_nodes: int | None = None, plan: EdgePlan | None = None) -> DistanceConv:
        """Binds the static graph that ``conv(x)`` uses (see the class docstring).
        ``num_nodes`` defaults to the length of ``node_weight`` or ``mask``, else to
        ``edge_index.max() + 1``. ``plan``: an :class:`EdgePlan` of the same
        ``edge_index`` to share between layers (checked). Returns the layer."""
        if num_nodes is None:
            sized = node_weight if node_weight is not None else mask
            num_nodes = len(sized) if sized is not None else \
                int(edge_index.max()) + 1 if edge_index.numel() else 0
        edge_weight = _distances(edge_weight)
        self._check_graph(edge_index, edge_weight, int(num_nodes), node_weight, mask)
        self.bound_edge_index, self.bound_edge_weight = edge_index, edge_weight
        self.bound_node_weight, self.bound_mask = node_weight, mask
        if plan is not None and not plan.matches(edge_index, int(num_nodes)):
            raise ValueError("plan was built for another graph than edge_index")
        self.plan = plan if plan is not None else EdgePlan(edge_index, int(num_nodes))
        self._coef, self._coef_key = None, None
        return self

    @staticmethod
    def _check_graph(edge_index, edge_weight, n, node_weight, mask) -> None:
        if edge_weight is None:
            raise ValueError("edge_weight (the distance of each edge) is required: a "
                             "distance-only kernel has nothing else to read")
        if edge_index.dim() != 2 or edge_index.shape[0] != 2 or \
                edge_weight.shape != (edge_index.shape[1],):
            raise ValueError(f"need edge_index [2, E] and edge_weight [E], got "
                             f"{tuple(edge_index.shape)} and {tuple(edge_weight.shape)}")
        if edge_index.numel() and not 0 <= int(edge_index.min()) <= int(edge_index.max()) < n:
            raise ValueError(f"edge_index refers to nodes outside [0, {n}) (the signal has {n} "
                             "points)")
        if not torch.isfinite(edge_weight).all():
            raise ValueError("edge_weight has NaN or inf distances")
        for name, t in (("node_weight", node_weight), ("mask", mask)):
            if t is not None and t.shape != (n,):
                raise ValueError(f"{name} must have shape [{n}] (one value per point), got "
                                 f"{tuple(t.shape)}")
        if node_weight is not None and not torch.isfinite(node_weight).all():
            raise ValueError("node_weight has NaN or inf")

    def _edge_coefficients(self, edge_index, edge_weight, num_nodes, node_weight, mask):
        """Per-edge factors phi_k(d_ij) w_j / norm_i ``[E, K]`` (K = hidden for mlp)."""
        j, i = edge_index
        phi = self.kernel(edge_weight)
        w = torch.ones(num_nodes, dtype=phi.dtype, device=phi.device)
        if self.normalize == "area" and node_weight is not None:
            w = node_weight.to(phi.dtype)
        if mask is not None:
            w = w * mask.to(phi.dtype)
        coef = phi * w[j, None]
        if self.normalize is not None:
            # sum_k phi_k for the positive bases; bases that change sign (bessel, mlp)
            # could cancel to ~0 there, so they normalize by the positive envelope
            mass = phi.sum(1) if self.kernel.positive and self.kernel_type == "basis" else \
                envelope(edge_weight / self.radius) * (edge_weight < self.radius)
            den = torch.zeros(num_nodes, dtype=phi.dtype, device=phi.device)
            den = den.index_add(0, i, mass * w[j])
            coef = coef / den.clamp_min(1e-12)[i, None]
        return coef

    def _bound_coefficients(self, mask):
        """The bound graph's coefficients: cached while nothing needs their gradient and
        the bound tensors are unchanged; recomputed for a per-call ``mask``."""
        ei, ew, nw = self.bound_edge_index, self.bound_edge_weight, self.bound_node_weight
        n = self.plan.num_nodes
        if mask is not None:
            return self._edge_coefficients(ei, ew, n, nw, mask)
        m = self.bound_mask
        grad = torch.is_grad_enabled() and (
            self.kernel.learnable or ew.requires_grad or (nw is not None and nw.requires_grad))
        if grad:
            return self._edge_coefficients(ei, ew, n, nw, m)
        key = tuple(None if t is None else (t._version, t.dtype, t.device)
                    for t in (ei, ew, nw, m))
        if self._coef is None or self._coef_key != key:
            with torch.no_grad():
                self._coef = self._edge_coefficients(ei, ew, n, nw, m)
            self._coef_key = key
        return self._coef

    # -- forward --------------------------------------------------------------------
    def forward(self, x: torch.Tensor, edge_index: torch.Tensor | None = None,
                edge_weight: torch.Tensor | None = None,
                node_weight: torch.Tensor | None = None, mask: torch.Tensor | None = None,
                fast: bool = True) -> torch.Tensor:
        if x.dim() not in (2, 3) or x.shape[-1] != self.in_channels:
            raise ValueError(f"x must be [N, {self.in_channels}] or [B, N, {self.in_channels}],"
                             f" got {tuple(x.shape)}")
        N = x.shape[-2]
        if edge_index is None:  # the bound static graph
            if self.plan is None:
                raise ValueError("no graph: pass edge_index and edge_weight, or bind() one")
            if edge_weight is not None or node_weight is not None:
                raise ValueError("edge_weight/node_weight without edge_index: pass the whole "
                                 "graph, or bind() it")
            if N != self.plan.num_nodes:
                raise ValueError(f"x has {N} points, the bound graph has {self.plan.num_nodes}")
            if mask is not None and mask.shape != (N,):
                raise ValueError(f"mask must have shape [{N}], got {tuple(mask.shape)}")
            edge_index, plan = self.bound_edge_index, self.plan
            coef = self._bound_coefficients(mask)
        else:
            edge_weight = _distances(edge_weight)
            self._check_graph(edge_index, edge_weight, N, node_weight, mask)
            plan = None
            coef = self._edge_coefficients(edge_index, edge_weight, N, node_weight, mask)
        coef = coef.to(x.dtype)
        if self.kernel_type == "mlp" or not fast:
            out = self._propagate(x, edge_index, coef, N)
        else:
            plan = plan if plan is not None else self._plan_of(edge_index, N)
            w = self.weight.view(self.num_basis, self.in_channels, self.out_channels)
            xb = (x if x.dim() == 3 else x.unsqueeze(0)).contiguous()
            out = basis_aggregate(xb, w.to(x.dtype), coef, plan)
            out = out if x.dim() == 3 else out[0]
        if self.bias is not None:
            out = out + self.bias
        return out

    def _plan_of(self, edge_index: torch.Tensor, N: int) -> EdgePlan:
        """The PyG form's plan: the last call's when ``edge_index`` is the same by value (a
        loader's batches of one grid are), else a new one on a copy of it, so that changing
        the caller's tensor in place cannot leave a stale plan matching."""
        plan = self._plans.get("last")
        if plan is None or plan.edge_index.device != edge_index.device or \
                not plan.matches(edge_index, N):
            plan = self._plans["last"] = EdgePlan(edge_index.clone(), N)
        return plan

    def _propagate(self, x, edge_index, coef, N):
        """Plain per-edge message passing: the reference path (and the mlp kernel)."""
        batched = x.dim() == 3
        xs = x.transpose(0, 1) if batched else x  # [N, (B,) C]
        out = self.propagate(edge_index, x=xs, coef=coef, size=(N, N))
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
        bound = "" if self.plan is None else \
            f", bound={self.plan.num_nodes} nodes/{self.plan.num_edges} edges"
        return (f"{type(self).__name__}({self.in_channels}, {self.out_channels}, "
                f"radius={self.radius:.4g}, num_basis={self.num_basis}, "
                f"basis='{self.kernel.basis}'{extra}, normalize={self.normalize!r}{bound})")


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


def _distances(edge_weight):
    """``[E, 1]`` edge attributes (PyG's ``Distance`` layout) as ``[E]`` distances."""
    if edge_weight is not None and edge_weight.dim() == 2 and edge_weight.shape[1] == 1:
        return edge_weight[:, 0]
    return edge_weight


class UprightConv(SphericalConv):
    r""":class:`SphericalConv` whose kernel also sees which way each neighbour lies relative
    to a given up direction: the anisotropic filters of a planar CNN, with the frame taken
    from up instead of from latitude and longitude.

    With :math:`a_{ijk}` the normalized coefficients of :class:`DistanceConv`,
    :math:`\mathbf{u}_{ij}` the unit tangent at :math:`\mathbf{p}_i` towards
    :math:`\mathbf{p}_j` (0 for j = i) and each sample's unit up :math:`\mathbf{g}`,

    .. math::
        \mathbf{y}_i = \sum_{k=1}^{K} \sum_j a_{ijk} \big(\mathbf{W}_k^\top
        + (s_{ij} - \bar s_{ik})\, \mathbf{U}_k^\top
        + (c_{ij} - \bar c_{ik})\, \mathbf{V}_k^\top\big) \mathbf{x}_j + \mathbf{b},
        \qquad s_{ij} = \mathbf{u}_{ij} \cdot \mathbf{g},\;
        c_{ij} = (\mathbf{p}_i \times \mathbf{u}_{ij}) \cdot \mathbf{g}

    where :math:`\bar s_{ik} = \sum_j a_{ijk} s_{ij} / \sum_j a_{ijk}` (and :math:`\bar c_{ik}`)
    are the means over the neighbours the kernel sees. :math:`s` and :math:`c` are the
    neighbour's direction along and across up's tangential part :math:`\mathbf{t}` (as in
    :class:`~usf_graph.nn.UpJet`: :math:`\mathbf{u} \cdot \mathbf{t}` and
    :math:`\mathbf{u} \cdot (\mathbf{t} \times \mathbf{p})`), scaled by
    :math:`|\mathbf{t}| = \sin\theta`, so the kernel turns isotropic at the zenith and the
    nadir, where the frame is undefined, without a jump. Taking out the means makes the
    oriented part blind to a constant signal, also where the mask cuts the neighbourhood
    in half: the border of a camera's field of view is not an edge. When the input and up
    rotate together nothing here changes, so the layer is exactly SO(3)-equivariant (for
    rotations that map the grid onto itself; up to discretization otherwise).

    Both forms of the graph, as :class:`DistanceConv`: ``conv.bind(edge_index, edge_weight,
    node_weight, mask, pos=pos)`` once, then ``conv(x, up, mask=None)``, 3K sparse products
    per sample on the CPU where :class:`SphericalConv` costs K (one per batch on a GPU); or
    PyG's ``conv(x, up, edge_index, edge_weight, node_weight, mask, pos=pos, batch=batch)``
    for a batch of different graphs,
    with one up per graph (the geometry computed in the call).

    Shapes: ``x [B, N, C_in]`` and ``up [B, 3]`` (unit), or ``x [sum N_i, C_in]`` and ``up
    [G, 3]``; ``pos [N, 3]``; output ``[B, N, C_out]`` or ``[sum N_i, C_out]``.
    """

    def __init__(self, in_channels: int, out_channels: int, radius: float, num_basis: int = 4,
                 basis: str = "hat", normalize: str | None = "area", bias: bool = True):
        super().__init__(in_channels, out_channels, radius, num_basis, "basis", basis, normalize,
                         bias)
        self.weight = nn.Parameter(torch.empty(3 * num_basis * in_channels, out_channels))
        self.register_buffer("directions", None, persistent=False)
        self._oriented = None  # (the coefficients it was made from, their oriented basis)
        self.reset_parameters()

    def bind(self, edge_index: torch.Tensor, edge_weight: torch.Tensor,
             node_weight: torch.Tensor | None = None, mask: torch.Tensor | None = None,
             num_nodes: int | None = None, plan: EdgePlan | None = None, *,
             pos: torch.Tensor | None = None) -> UprightConv:
        """:meth:`DistanceConv.bind` plus ``pos [N, 3]``, the unit points, from which each
        edge's ``u_ij`` and ``p_i x u_ij`` are computed once."""
        if pos is None:
            raise ValueError("UprightConv.bind needs pos [N, 3]: the directions to the "
                             "neighbours are read from the points")
        super().bind(edge_index, edge_weight, node_weight, mask, num_nodes, plan)
        if pos.shape != (self.plan.num_nodes, 3):
            raise ValueError(f"pos must be [{self.plan.num_nodes}, 3], got {tuple(pos.shape)}")
        self.directions = _edge_directions(edge_index, pos)
        return self

    def forward(self, x: torch.Tensor, up: torch.Tensor, edge_index: torch.Tensor | None = None,
                edge_weight: torch.Tensor | None = None, node_weight: torch.Tensor | None = None,
                mask: torch.Tensor | None = None, pos: torch.Tensor | None = None,
                batch: torch.Tensor | None = None) -> torch.Tensor:
        """The bound graph: ``conv(x [B, N, C], up [B, 3], mask=None)``. PyG's form, any
        graphs: ``conv(x [N, C], up [G, 3], edge_index, edge_weight, node_weight, mask,
        pos=pos, batch=batch)``, one up per graph (``batch``: each point's graph)."""
        if edge_index is not None:
            return self._general(x, up, edge_index, edge_weight, node_weight, mask, pos, batch)
        if self.directions is None:
            raise ValueError("UprightConv needs a graph: bind(edge_index, edge_weight, ..., "
                             "pos=pos) first, or pass edge_index, edge_weight and pos")
        if x.dim() != 3 or x.shape[-1] != self.in_channels or x.shape[1] != self.plan.num_nodes:
            raise ValueError(f"x must be [B, {self.plan.num_nodes}, {self.in_channels}], got "
                             f"{tuple(x.shape)}")
        if up is None or up.shape != (len(x), 3):
            raise ValueError(f"up must be [{len(x)}, 3] (one unit up per sample), got "
                             f"{None if up is None else tuple(up.shape)}")
        if mask is not None and mask.shape != (x.shape[1],):
            raise ValueError(f"mask must have shape [{x.shape[1]}], got {tuple(mask.shape)}")
        coef = self._bound_coefficients(mask)
        basis = self._bound_basis(coef, x.dtype)
        coef = coef.to(x.dtype)
        ang = (basis.reshape(-1, 3) @ up.to(x.dtype).t()).view(len(coef), -1, len(x))  # [E, 2K, B]
        w = self.weight.view(3 * self.num_basis, self.in_channels, self.out_channels).to(x.dtype)
        full = torch.cat([coef.expand(len(x), -1, -1), ang.permute(2, 0, 1)], 2)  # [B, E, 3K]
        out = basis_aggregate(x.contiguous(), w, full, self.plan)
        return out if self.bias is None else out + self.bias

    def _bound_basis(self, coef: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        """:func:`oriented_basis` of the bound graph for its coefficients ``coef``. Kept
        while they are the cached ones (one ``[E, 2K, 3]`` per graph and mask instead of
        ``[B, E, 2K]`` centred products per call); never with an autograd graph."""
        cached = self._oriented
        if cached is not None and cached[0] is coef and cached[1].dtype == dtype:
            return cached[1]
        basis = oriented_basis(coef.to(dtype), self.directions.to(dtype),
                               self.bound_edge_index[1], self.plan.num_nodes)
        if coef is self._coef:  # a per-call mask's or a learnable kernel's: not kept
            self._oriented = (coef, basis)
        return basis

    def _general(self, x, up, edge_index, edge_weight, node_weight, mask, pos, batch):
        """PyG's form: a batch of different graphs is one graph of disjoint parts, each edge
        reading its own graph's up, so the sparse kernel of the bound form serves it too."""
        if x.dim() != 2 or x.shape[-1] != self.in_channels:
            raise ValueError(f"x must be [N, {self.in_channels}] with edge_index, got "
                             f"{tuple(x.shape)}")
        N = len(x)
        if pos is None or pos.shape != (N, 3):
            raise ValueError(f"pos must be [{N}, 3] (the points): the directions to the "
                             "neighbours are read from them")
        graphs = 1 if batch is None else int(batch.max()) + 1 if N else 0
        if up is None or up.shape != (graphs, 3):
            raise ValueError(f"up must be [{graphs}, 3] (one unit up per graph), got "
                             f"{None if up is None else tuple(up.shape)}")
        edge_weight = _distances(edge_weight)
        self._check_graph(edge_index, edge_weight, N, node_weight, mask)
        coef = self._edge_coefficients(edge_index, edge_weight, N, node_weight, mask).to(x.dtype)
        i = edge_index[1]
        g = up.to(x.dtype)[0 if batch is None else batch[i]].expand(len(i), 3)
        side = torch.einsum("emc,ec->em", _edge_directions(edge_index, pos).to(x.dtype), g)
        full = torch.cat([coef, oriented_basis(coef, side, i, N)], 1)  # [E, 3K]
        w = self.weight.view(len(full[0]), self.in_channels, self.out_channels).to(x.dtype)
        out = basis_aggregate(x[None].contiguous(), w, full, self._plan_of(edge_index, N))[0]
        return out if self.bias is None else out + self.bias


def _edge_directions(edge_index: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
    """``[E, 2, 3]`` float64: for each edge ``j -> i``, the unit tangent ``u`` at ``p_i``
    towards ``p_j`` (0 on a self-loop) and ``p_i x u``."""
    j, i = edge_index
    unit = pos.double() / pos.double().norm(dim=-1, keepdim=True)
    p = unit[i]
    u = torch.where((i == j)[:, None], 0.0, tangent_towards(p, unit[j]))  # a self-loop: none
    return torch.stack([u, torch.linalg.cross(p, u)], 1)


def oriented_basis(coef: torch.Tensor, directions: torch.Tensor, i: torch.Tensor,
                   n: int) -> torch.Tensor:
    r""":class:`UprightConv`'s oriented coefficients :math:`a_{ijk} (s_{ij} - \bar s_{ik})`
    (the K along up) and :math:`a_{ijk} (c_{ij} - \bar c_{ik})` (the K across), ``[E, 2K,
    ...]``, from the distance coefficients ``coef [E, K]``, each edge's centre ``i [E]``
    among ``n`` points and its ``directions [E, 2, ...]``: ``u`` and ``p_i x u`` (``[E, 2,
    3]``, giving a linear map to take with a unit up) or their products with the edge's
    up (``[E, 2]``). Both the direction and its mean over a centre's neighbours are linear
    in up, so with ``[E, 2, 3]`` the map is built once per graph and mask and each
    sample's up costs one small product."""
    ones = (1,) * (directions.dim() - 2)
    c = coef.view(*coef.shape, 1, *ones)  # [E, K, 1, ...]
    ang = c * directions[:, None]  # [E, K, 2, ...]
    total = coef.new_zeros(n, coef.shape[1]).index_add_(0, i, coef).clamp_min(1e-12)
    mean = ang.new_zeros(n, *ang.shape[1:]).index_add_(0, i, ang) / total.view(*total.shape, 1, *ones)
    ang = ang - c * mean[i]
    return ang.transpose(1, 2).reshape(len(coef), -1, *directions.shape[2:])  # along up first
