"""UprightConv: distance kernels plus oriented ones in the frame of a given up direction."""

from __future__ import annotations

import contextlib

import torch
from torch import nn

from ..geometry import tangent_towards
from ..sparse import kept
from ..tracing import exporting
from .aggregate import EdgePlan, basis_aggregate
from .conv import SphericalConv, _distances
from .precision import accumulate_in


class UprightConv(SphericalConv):
    r""":class:`~usf_graph.nn.SphericalConv` whose kernel also sees which way each neighbour lies relative
    to a given up direction: the anisotropic filters of a planar CNN, with the frame taken
    from up instead of from latitude and longitude.

    With :math:`a_{ijk}` the normalized coefficients of :class:`~usf_graph.nn.DistanceConv`,
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

    Both forms of the graph, as :class:`~usf_graph.nn.DistanceConv`: ``conv.bind(edge_index, edge_weight,
    node_weight, mask, pos=pos)`` once, then ``conv(x, up, mask=None)``, 3K sparse products
    per sample on the CPU where :class:`~usf_graph.nn.SphericalConv` costs K (one per batch on a GPU); or
    PyG's ``conv(x, up, edge_index, edge_weight, node_weight, mask, pos=pos, batch=batch)``
    for a batch of different graphs,
    with one up per graph (the geometry computed in the call). In PyG's explain mode
    (``torch_geometric.explain``) the explainer's edge mask scales each edge's coefficients,
    hence its message.

    Shapes: ``x [B, N, C_in]`` and ``up [B, 3]`` (unit), or ``x [sum N_i, C_in]`` and ``up
    [G, 3]``; ``pos [N, 3]``; output ``[B, N, C_out]`` or ``[sum N_i, C_out]``.
    """

    def __init__(self, in_channels: int, out_channels: int, radius: float, num_basis: int = 4,
                 basis: str = "hat", normalize: str | None = "area", bias: bool = True):
        super().__init__(in_channels, out_channels, radius, num_basis, "basis", basis, normalize,
                         bias)
        self.weight = nn.Parameter(torch.empty(3 * num_basis * in_channels, out_channels))
        self.register_buffer("directions", None, persistent=False)
        self._oriented: dict = {}  # per coefficient slot: (the coefficients, their oriented basis)
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
        if self._message_hooks():  # rather than never call them without a word
            raise ValueError("UprightConv passes no per-edge messages, so PyG's propagate, "
                             "message and aggregate hooks are never called on it; use torch's "
                             "register_forward_hook on the layer instead")
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
        acc = accumulate_in(x.dtype)
        coef = self._bound_coefficients(mask, acc)
        basis = self._bound_basis(coef, acc)  # [3, 2K E]
        ang = (up.to(acc) @ basis).view(len(x), -1, len(coef))  # [B, 2K, E], written in order
        w = self.weight.view(3 * self.num_basis, self.in_channels, self.out_channels).to(acc)
        # [B, E, 3K] as a view of [B, 3K, E]: the sparse kernel reads each basis function's
        # values as one contiguous row, so it need not transpose every sample's copy
        full = torch.cat([coef.t().expand(len(x), -1, -1), ang], 1).transpose(1, 2)
        full = self._explained(full)
        out = basis_aggregate(x.contiguous(), w, full, self.plan)
        return out if self.bias is None else out + self.bias

    def _bound_basis(self, coef: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        """:func:`oriented_basis` of the bound graph for its coefficients ``coef``, laid out
        ``[3, 2K E]`` so that each call's ``up @ basis`` writes ``[B, 2K, E]`` in the order
        the sparse kernel reads (a transposing copy of ``[E, 2K, B]`` took 2x as long). Kept
        while they are cached ones (one per graph and mask instead of ``[B, E, 2K]``
        centred products per call): the bound mask's and the last per-call mask's, as the
        coefficients are; never with an autograd graph."""
        slot = "bound" if coef is self._coef else "call" if coef is self._call_coef else None
        cached = self._oriented.get(slot)
        # while exporting, the module's tensor attributes (the bound coefficients) are fakes
        # of those the eager call before kept: the slot names them, and nothing is stored
        if cached is not None and (cached[0] is coef or exporting()) and cached[1].dtype == dtype:
            return cached[1]
        # coefficients that need a gradient are not cached ones, nor is their basis
        with contextlib.nullcontext() if slot is None else kept():
            basis = oriented_basis(coef.to(dtype), self.directions.to(dtype),
                                   self.bound_edge_index[1], self.plan.num_nodes)
            basis = basis.permute(2, 1, 0).reshape(3, -1)
        if slot is not None and not exporting():
            self._oriented[slot] = (coef, basis)
        return basis

    def _explained(self, full: torch.Tensor) -> torch.Tensor:
        """The coefficients ``full [..., E, 3K]``, in PyG's explain mode scaled by the
        explainer's edge mask: a message is linear in its edge's coefficients, so this is
        the mask scaling each message, as PyG's explainers do."""
        m = self._explain_mask(full.shape[-2])
        return full if m is None else full * m.to(full.dtype)[:, None]

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
        acc = accumulate_in(x.dtype)
        coef = self._edge_coefficients(edge_index, edge_weight, N, node_weight, mask).to(acc)
        i = edge_index[1]
        g = up.to(acc)[0 if batch is None else batch[i]].expand(len(i), 3)
        side = torch.einsum("emc,ec->em", _edge_directions(edge_index, pos).to(acc), g)
        full = self._explained(torch.cat([coef, oriented_basis(coef, side, i, N)], 1))  # [E, 3K]
        w = self.weight.view(len(full[0]), self.in_channels, self.out_channels).to(acc)
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
