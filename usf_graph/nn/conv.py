"""SphericalConv / PointConv: convolution with a kernel of distance only."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn
from torch_geometric.nn import MessagePassing

from ..sparse import kept, version
from ..tracing import exporting, field_of, note_field
from .aggregate import EdgePlan, basis_aggregate
from .kernel import DistanceKernel, envelope
from .precision import GeometryModule, accumulate_in

NORMALIZE = ("area", "mean", None)


class DistanceConv(GeometryModule, MessagePassing):
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
      for that call, and its coefficients are kept too, beside the bound mask's, for the
      next call whose mask is equal by value (a camera's field of view, frame after
      frame). Bind again to change the graph; in-place edits of the bound tensors
      are noticed through their version counters. ``reset_parameters`` clears the cached
      coefficients. Geometry is never matched to inputs by memory address.

    With ``kernel="basis"`` a forward pass is K sparse products and K dense GEMMs per
    sample on the CPU, and one of each for the whole batch on a GPU
    (:func:`~usf_graph.nn.aggregate.basis_aggregate`); gradients reach ``x``, the
    weights and the coefficients, hence ``edge_weight``, ``node_weight`` and a learnable
    basis, and with ``create_graph=True`` they can be differentiated again (gradient
    penalties, Hessian-vector products). ``kernel="mlp"`` makes a per-edge :math:`C_{in} \times C_{out}` weight from an MLP
    of the distance (slower; for expressivity studies), by message passing, as does
    ``fast=False`` (the plain per-edge reference), PyG's explain mode (so that
    ``torch_geometric.explain``, e.g. ``GNNExplainer``, masks and scores this layer's edges)
    and a layer with PyG's ``propagate``, ``message`` or ``aggregate`` hooks registered
    (the messages they see are ``[E, K, (B,) C_in]``: each neighbour's features times its
    basis coefficients, before the weights).

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
        for name, n in (("in_channels", in_channels), ("out_channels", out_channels), ("hidden", hidden)):
            if int(n) != n or n < 1:
                raise ValueError(f"{name} must be a positive integer, got {n!r}")
        if not (math.isfinite(radius) and radius > 0):
            raise ValueError(f"radius must be a positive finite geodesic distance in radians (or "
                             f"a distance in R3), got {radius!r}")
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
        self._coef_key = None  # the versions the bound mask's coefficients were computed from
        self._call = None  # the last per-call mask: (a copy of it, its key, its coefficients, its values)
        self._plans: dict = {}  # PyG form: the last graph's plan (a dict: not a submodule)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        super().reset_parameters()
        self.kernel.reset_parameters()
        bound = (3.0 / self.weight.shape[0]) ** 0.5  # variance 1 / fan-in (K C_in; hidden)
        nn.init.uniform_(self.weight, -bound, bound)
        if self.bias is not None:
            nn.init.zeros_(self.bias)
        self._forget()

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
        self._forget()
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
        if node_weight is not None and not (torch.isfinite(node_weight) & (node_weight >= 0)).all():
            raise ValueError("node_weight must hold areas: finite and >= 0 (NaN, inf or a "
                             "negative value found)")

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

    def _bound_coefficients(self, mask, dtype):
        """The bound graph's coefficients in ``dtype``: cached while nothing needs their
        gradient and the bound tensors are unchanged. A per-call ``mask`` replaces the
        bound one; the last one's coefficients are cached too, beside the bound mask's,
        matched by value (a camera's field of view, frame after frame, is geometry). Not
        a buffer: ``.to()`` changes the key (the bound tensors' dtype and device), so the
        entry is then recomputed."""
        ei, ew, nw = self.bound_edge_index, self.bound_edge_weight, self.bound_node_weight
        n, m = self.plan.num_nodes, self.bound_mask if mask is None else mask
        grad = torch.is_grad_enabled() and (
            self.kernel.learnable or ew.requires_grad or (nw is not None and nw.requires_grad))
        bound = (ei, ew, nw, self.bound_mask)
        versions = [None if t is None else version(t) for t in bound]
        note_field(mask)
        if exporting():
            return self._traced_coefficients(mask, dtype)
        if grad or any(t is not None and v is None for t, v in zip(bound, versions)):
            # a graph built in inference mode has no versions to check a kept entry against
            return self._edge_coefficients(ei, ew, n, nw, m).to(dtype)
        key = tuple(None if t is None else (v, t.dtype, t.device)
                    for t, v in zip(bound, versions)) + (dtype,)
        # each entry is read once and the local value returned: a thread calling with
        # another mask or dtype between the check and the return cannot hand this call
        # its coefficients
        if mask is None:
            coef = self._coef
            if coef is None or self._coef_key != key:
                with kept():
                    coef = self._edge_coefficients(ei, ew, n, nw, m).to(dtype)
                self._coef, self._coef_key = coef, key
            return coef
        call = self._call
        if call is not None and call[1] == key and _same(call[0], mask):
            return call[2]
        with kept():
            coef = self._edge_coefficients(ei, ew, n, nw, m).to(dtype)
            self._call = (mask.detach().clone(), key, coef, mask.detach().cpu().numpy().copy())
        return coef

    def _traced_coefficients(self, mask, dtype) -> torch.Tensor:
        """While exporting: the coefficients an eager call kept for this field of view
        (geometry, so the exported graph holds them as constants), else computed in the
        graph from the traced inputs."""
        kept_ = self._coef if mask is None else \
            None if self._call is None or not np.array_equal(self._call[3], field_of(mask)) \
            else self._call[2]
        if kept_ is not None and kept_.dtype == dtype:
            return kept_
        m = self.bound_mask if mask is None else mask
        return self._edge_coefficients(self.bound_edge_index, self.bound_edge_weight,
                                       self.plan.num_nodes, self.bound_node_weight, m).to(dtype)

    @property
    def _call_coef(self) -> torch.Tensor | None:
        """The last per-call mask's cached coefficients (None: none yet)."""
        return None if self._call is None else self._call[2]

    def _forget(self) -> None:
        """Drops the cached coefficients (new parameters or a new graph)."""
        self._coef, self._coef_key, self._call = None, None, None

    # -- forward --------------------------------------------------------------------
    def forward(self, x: torch.Tensor, edge_index: torch.Tensor | None = None,
                edge_weight: torch.Tensor | None = None,
                node_weight: torch.Tensor | None = None, mask: torch.Tensor | None = None,
                fast: bool = True) -> torch.Tensor:
        """``y`` ``[N, C_out]`` or ``[B, N, C_out]`` (class docstring's equation).

        ``edge_index``/``edge_weight`` (and optionally ``node_weight``, ``mask``) give the graph for
        this call; without them the bound graph is used (``mask`` may still replace the bound
        one). ``fast=False`` runs the per-edge message-passing reference instead of the sparse
        products (the same result, for tests).
        """
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
            coef = self._bound_coefficients(mask, accumulate_in(x.dtype))
        else:
            edge_weight = _distances(edge_weight)
            self._check_graph(edge_index, edge_weight, N, node_weight, mask)
            plan = None
            coef = self._edge_coefficients(edge_index, edge_weight, N, node_weight, mask) \
                .to(accumulate_in(x.dtype))
        if self.kernel_type == "mlp" or not fast or self._wants_messages():
            out = self._propagate(x, edge_index, coef.to(x.dtype), N)
        else:
            plan = plan if plan is not None else self._plan_of(edge_index, N)
            w = self.weight.view(self.num_basis, self.in_channels, self.out_channels)
            xb = (x if x.dim() == 3 else x.unsqueeze(0)).contiguous()
            out = basis_aggregate(xb, w.to(coef.dtype), coef, plan)
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
            with kept():  # kept for later calls: no transform's wrappers
                plan = self._plans["last"] = EdgePlan(edge_index.clone(), N)
        return plan

    def _wants_messages(self) -> bool:
        """Whether PyG's machinery needs the per-edge messages: its explain mode, or hooks
        registered on ``propagate``, ``message`` or ``aggregate``."""
        return bool(self.explain) or self._message_hooks()

    def _message_hooks(self) -> bool:
        """Whether PyG's ``propagate``, ``message`` or ``aggregate`` hooks are registered."""
        return any(map(bool, (
            self._propagate_forward_pre_hooks, self._propagate_forward_hooks,
            self._message_forward_pre_hooks, self._message_forward_hooks,
            self._aggregate_forward_pre_hooks, self._aggregate_forward_hooks)))

    def _explain_mask(self, num_edges: int) -> torch.Tensor | None:
        """In PyG's explain mode, the explainer's edge mask ``[E]`` as it scales each
        message (its sigmoid where the explainer asks for one); else None."""
        if not self.explain:
            return None
        m = getattr(self, "_edge_mask", None)
        if m is None:
            raise ValueError("explain mode without an edge mask: let an Explainer set one, or "
                             "torch_geometric.explain.algorithm.utils.set_masks")
        if m.numel() != num_edges:
            raise ValueError(f"the explainer's edge mask has {m.numel()} entries, this layer's "
                             f"graph {num_edges} edges: explain the model with the edge_index "
                             "its layers use (a bound layer: its bound one)")
        return m.sigmoid() if self._apply_sigmoid else m

    def _propagate(self, x, edge_index, coef, N):
        """Plain per-edge message passing: the reference path, the mlp kernel, and PyG's
        explain mode (its edge mask scales each message)."""
        self._explain_mask(edge_index.shape[1])  # checked; PyG's propagate applies it
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


def _same(cached: torch.Tensor | None, mask: torch.Tensor | None) -> bool:
    """Whether a per-call mask equals the cached one by value (both None: no mask)."""
    if cached is None or mask is None:
        return cached is None and mask is None
    return cached.shape == mask.shape and cached.dtype == mask.dtype and \
        cached.device == mask.device and bool(torch.equal(cached, mask))
