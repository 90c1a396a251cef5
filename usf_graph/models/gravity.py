r"""Which way is up? An SO(3)-equivariant estimate of gravity from a spherical image.

A planar network trained on upright panoramas reads "ceiling above, floor below" from the
pixel rows; an equivariant network has no rows. :class:`GravityHead` gives it the cue
back without breaking equivariance: it scores every candidate direction as the up
direction with a whole-sphere distance-kernel convolution of the image's features, and
the estimate rotates with the input. Each point's height along it (:func:`heights`) is
then a rotation-invariant feature.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from ..frontend import grid_graph
from ..geometry import geodesic_distance
from ..grids import icosahedral
from ..nn import FillHidden, SurfaceJet
from ..nn.precision import GeometryModule
from ..tracing import check_values, field_of

#: Below this :class:`GravityHead` ``margin`` (score units) an up estimate is ambiguous
#: between vanishing directions; read off the rooms protocols' test views (README).
UNSURE_MARGIN = 1.0


def heights(pos: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    """``p . up`` for points ``pos [N, 3]`` and directions ``up [B, 3]`` -> ``[B, N, 1]``."""
    return (pos.to(up.dtype) @ up.T).T[..., None]


def level_scores(candidates: torch.Tensor, pos: torch.Tensor, area: torch.Tensor,
                 mask: torch.Tensor, strength: float) -> torch.Tensor:
    r"""Scores ``[Nc]`` for a camera mounted level, to add to a :class:`GravityHead`'s:
    :math:`-\beta\,(a_n \cdot m)^2 / \lVert m \rVert` for the candidates :math:`a_n`
    (``candidates [Nc, 3]``), with :math:`m` the area-weighted mean of the points ``pos
    [N, 3]`` (areas ``area [N]``) that the field of view ``mask [N]`` sees, and
    :math:`\beta` = ``strength``. Up is perpendicular to a level camera's optical axis,
    which :math:`m` points along: about :math:`-\beta` for a candidate on the axis of a
    90-degree pinhole (:math:`\lVert m \rVert = 0.83`), :math:`-\beta / 2` for a
    190-degree fisheye (0.46), 0 for the whole sphere (:math:`m = 0`)."""
    if not field_of(mask).any():
        raise ValueError("level_scores: the field of view (mask) sees no point")
    w = area * mask.to(area.dtype)
    m = (w[:, None] * pos).sum(0) / w.sum()
    return -strength * (candidates @ m) ** 2 / m.norm().clamp_min(1e-12)


def pick_axis(logits: torch.Tensor, candidates: torch.Tensor, axes: torch.Tensor) -> torch.Tensor:
    """A :class:`GravityHead`'s choice of up among given directions: of each view's
    ``axes [B, 3, 3]`` (rows, each up to sign; e.g. the Manhattan axes of the image's
    straight lines, :func:`usf_graph.frontend.lines.manhattan_axes`), the signed one whose
    nearest candidate (``candidates [Nc, 3]``) the head scores highest (``logits [B, Nc]``)
    -> ``[B, 3]``. The head tells which of a room's vanishing directions is up; the lines
    place it to a degree or two, where the head's candidates are 8 degrees apart."""
    if axes.dim() != 3 or axes.shape[1:] != (3, 3) or len(axes) != len(logits):
        raise ValueError(f"axes must be [B, 3, 3] for {len(logits)} views, got {tuple(axes.shape)}")
    signed = torch.cat([axes, -axes], 1).to(candidates.dtype)  # [B, 6, 3]
    near = (signed @ candidates.T).argmax(-1)  # [B, 6]
    best = logits.gather(1, near).argmax(-1)
    return signed[torch.arange(len(signed), device=signed.device), best]


class GravityHead(GeometryModule):
    r"""Estimates the up direction of a spherical image, SO(3)-equivariantly.

    Every candidate direction :math:`a_n` (the points of ``icosahedral(candidate_level)``)
    gets a score from the coarse features :math:`f_m` at points :math:`p_m`,

    .. math::
        U_n = \frac{\sum_m w_m \sum_k \varphi_k(\theta_{nm})\, W_k f_m}{\sum_m w_m},
        \qquad s_n = v^\top \mathrm{ReLU}(U_n + b),

    with :math:`\theta_{nm}` the geodesic distance from :math:`a_n` to :math:`p_m`,
    ``num_basis`` Gaussian bumps :math:`\varphi_k` over :math:`[0, \pi]` (centred at
    :math:`k\pi / (K - 1)`, as wide as that spacing), and :math:`w` the grid's areas
    inside the field of view. This is a distance-kernel convolution with a
    whole-sphere support evaluated at the candidates: it asks, for each candidate, "does
    the scene look upright if this is up?" (ceiling-like content near it, floor-like
    content opposite, furniture below the horizon), which needs no single point to know
    its own elevation. The estimate is the soft-argmax of the scores over the candidates
    within ``window`` radians of the best one, :math:`\hat u = \mathrm{normalize}(\sum_n
    \pi_n a_n)`. It rotates with the input (exactly for rotations of the grids onto
    themselves); candidates cover the whole sphere, so up may lie outside the lens's field
    of view. Trained by :meth:`loss` on views of known gravity, which also asks a linear map
    of the features for each point's height :math:`p_m \cdot g` (a dense, invariant
    target that the 200 up directions of a small training set alone do not give).

    **How sure it is.** ``margin`` is :math:`\max_n s_n - \max_{n:\ \angle(a_n, a^*) >
    \text{rival}} s_n`, how much better the scene looks upright about the best candidate
    :math:`a^*` than about any direction at least ``rival`` radians (45 degrees) from it. A
    room has three vanishing directions and the estimate's gross errors are a wrong one of
    them, about 90 degrees off, mostly chosen by a small margin: on the rooms protocols'
    test panoramas and fisheye views, 17 of the 20 estimates more than 60 degrees off had a
    margin below :data:`UNSURE_MARGIN`, against 10-22% of all views (docs/up_estimate.md,
    "How sure is the up estimate?"). It is invariant, like the scores' ranking. Below it, prefer a known
    up (an IMU) where there is one.

    Shapes: features ``[B, M, C]`` on ``coarse``, ``mask [M]`` or ``None`` ->
    ``{"up": [B, 3], "logits": [B, Nc], "margin": [B], "height": [B, M], "weight": [M]}``
    (``weight``: the visible areas).
    """

    def __init__(self, coarse, channels: int, hidden: int = 32, num_basis: int = 8,
                 candidate_level: int = 3, window: float = math.radians(20),
                 concentration: float = 100.0, rival: float = math.radians(45)):
        super().__init__()
        self.hidden, self.num_basis = hidden, num_basis
        self.window, self.concentration, self.rival = window, concentration, rival
        cand = icosahedral(candidate_level).pos.double()
        theta = geodesic_distance(cand[:, None], coarse.pos.double()[None])  # [Nc, M]
        centers = torch.linspace(0, math.pi, num_basis, dtype=torch.float64)
        width = math.pi / (num_basis - 1)
        phi = torch.exp(-0.5 * ((theta[None] - centers[:, None, None]) / width) ** 2)
        # float64 (cast at use): float32 would break the grid's symmetry in the last bit
        self.register_buffer("phi", phi, persistent=False)  # [K, Nc, M]
        self.register_buffer("candidates", cand, persistent=False)
        self.register_buffer("area", coarse.area.double(), persistent=False)
        self.register_buffer("pos", coarse.pos.double(), persistent=False)
        self.field = nn.Linear(channels, num_basis * hidden)
        self.height = nn.Linear(channels, 1)
        self.bias = nn.Parameter(torch.zeros(hidden))
        self.score = nn.Linear(hidden, 1)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Re-initializes the convolutions and the score; the candidates' bias starts at 0."""
        self.field.reset_parameters()
        self.height.reset_parameters()
        self.score.reset_parameters()
        nn.init.zeros_(self.bias)

    def forward(self, f: torch.Tensor, mask: torch.Tensor | None = None,
                extra: torch.Tensor | None = None) -> dict:
        """``extra [B, Nc]``: scores from elsewhere (:class:`EdgeVotes`), added to the
        logits before the estimate."""
        B, M, _ = f.shape
        w = self.area.to(f.dtype) * (1 if mask is None else mask.to(f.dtype))
        z = self.field(f).view(B, M, self.num_basis, self.hidden) * (w / w.sum())[:, None, None]
        U = torch.einsum("knm,bmkh->bnh", self.phi.to(f.dtype), z)
        logits = self.score(torch.relu(U + self.bias))[..., 0]  # [B, Nc]
        if extra is not None:
            logits = logits + extra
        if check_values() and not torch.isfinite(logits).all():
            raise ValueError("the up estimate's scores are NaN or inf: its weights or its input "
                             "are not finite (a diverged training run?)")
        cand = self.candidates.to(f.dtype)
        best = cand[logits.argmax(-1)]  # [B, 3]
        cos = best @ cand.T
        p = torch.softmax(logits.masked_fill(cos <= math.cos(self.window), float("-inf")), -1)
        up = p @ cand
        rival = logits.masked_fill(cos >= math.cos(self.rival), float("-inf")).amax(-1)
        return {"up": up / up.norm(dim=-1, keepdim=True).clamp_min(1e-12), "logits": logits,
                "margin": logits.amax(-1) - rival, "height": self.height(f)[..., 0], "weight": w}

    def target(self, g: torch.Tensor) -> torch.Tensor:
        r"""The distribution over candidates the scores are trained towards for the true up
        ``g [B, 3]``: :math:`q_n \propto \exp(\kappa\, a_n \cdot g)` (``concentration``
        :math:`\kappa`; 100 is about 6 degrees wide) -> ``[B, Nc]``."""
        return torch.softmax(self.concentration * g @ self.candidates.to(g.dtype).T, -1)

    def loss(self, out: dict, g: torch.Tensor, sign_weight: float = 0.0) -> torch.Tensor:
        r"""Cross-entropy of the scores (:meth:`forward`'s ``out``) against :meth:`target`,
        plus (when ``out`` has ``height``) the area-weighted squared error of the heights
        over the visible points.

        ``sign_weight`` :math:`w`: plus :math:`w\,\mathrm{softplus}(s(-g) - s(g))`, with
        :math:`s(v) = \sum_n q_n(v)\, \ell_n` the scores weighted by :meth:`target`: a
        penalty on scoring down above up, which the cross-entropy counts as one wrong
        candidate among hundreds, while about half of the estimate's gross errors on
        partial views are upside down (docs/seg_det_log.md, session 26)."""
        logits = out["logits"]
        g = g.to(logits.dtype)
        q = self.target(g)
        ce = -(q * torch.log_softmax(logits, -1)).sum(-1).mean()
        if sign_weight:
            ce = ce + sign_weight * nn.functional.softplus(
                ((self.target(-g) - q) * logits).sum(-1)).mean()
        if "height" not in out:
            return ce
        w = out["weight"]
        h = heights(self.pos, g)[..., 0]
        return ce + ((out["height"] - h) ** 2 * w).sum(-1).mean() / w.sum()


class EdgeVotes(GeometryModule):
    r"""Vanishing-direction votes for the up direction from the image's edges.

    Vertical lines (room corners, door frames, furniture legs) all lie on great circles
    through the up direction, so at each such edge point :math:`p_m` the image gradient
    is orthogonal to up. With the colour gradients :math:`g_{mc}` (:class:`SurfaceJet`,
    exact 3D tangent vectors) and the structure tensor :math:`T_m = \sum_c g_{mc} g_{mc}^\top`,
    a candidate :math:`a_n` gets

    .. math::
        V_n = \frac{\sum_m \omega_m s_{nm}^2 \exp(-\kappa\, e_{nm})}{\sum_m \omega_m},
        \qquad e_{nm} = \frac{a_n^\top T_m a_n}{\operatorname{tr}(T_m)\, s_{nm}^2},
        \quad s_{nm}^2 = 1 - (a_n \cdot p_m)^2,

    :math:`e_{nm}` being the squared sine of the angle between the edge's great circle and
    :math:`a_n`. The learned weights :math:`\omega_m = \mathrm{softplus}(u^\top f_m) \ge 0`
    (invariant features) pick the edges that are vertical lines; votes come from the
    ``topk`` strongest visible edges. Both :math:`a_n^\top T_m a_n` and the features
    rotate with the input, so the votes are equivariant. This geometric cue sharpens an
    estimate from content alone (trained on 400 rooms, tested on 50 new ones: median error
    8.1 -> 5.9-6.7 degrees, 90th percentile 48 -> 13-18; README).

    Shapes: ``x [B, N, C]`` (the image, hidden points filled), ``f [B, N, F]``,
    ``mask [N]`` or ``None`` -> votes ``[B, Nc]`` (scaled by a learned factor).
    """

    def __init__(self, grid, candidates: torch.Tensor, features: int, spacing: float,
                 kappa: float = 20.0, topk: int = 512):
        super().__init__()
        self.kappa, self.topk = kappa, topk
        self.jet = SurfaceJet(grid.pos, *grid_graph(grid, 2.5 * spacing), spacing)
        self.register_buffer("cos", candidates.double() @ grid.pos.double().T,
                             persistent=False)  # [Nc, N]
        self.register_buffer("candidates", candidates.double(), persistent=False)
        self.weight = nn.Linear(features, 1)
        self.scale = nn.Parameter(torch.tensor(10.0))

    def reset_parameters(self) -> None:
        """Re-initializes the edge weights; the votes' scale starts at 10."""
        self.weight.reset_parameters()
        nn.init.constant_(self.scale, 10.0)

    def forward(self, x: torch.Tensor, f: torch.Tensor, mask: torch.Tensor | None = None
                ) -> torch.Tensor:
        """Votes ``[B, Nc]`` for every candidate direction, from ``x [B, N, C]``, ``f [B, N, F]``
        and ``mask [N]``.
        """
        idx, T, tr, vis = strongest_edges(self.jet, x, mask, self.topk)
        om = nn.functional.softplus(self.weight(f.gather(1, idx[..., None].expand(
            -1, -1, f.shape[-1]))))[..., 0] * vis  # hidden points never vote
        a = self.candidates.to(x.dtype)
        s2 = (1 - self.cos[:, idx].permute(1, 0, 2).to(x.dtype) ** 2).clamp_min(0)  # [B, Nc, K]
        # a squared sine, >= 0: T's rounding makes a^T T a slightly negative where a is
        # near the edge point (s2 -> 0), and exp(-kappa e) would blow that up (inf at level 5)
        e = (torch.einsum("ni,bkij,nj->bnk", a, T, a) / (tr[:, None] * s2 + 1e-6)).clamp_min(0)
        votes = (om[:, None] * s2 * torch.exp(-self.kappa * e)).sum(-1)
        return self.scale * votes / om.sum(-1, keepdim=True).clamp_min(1e-6)


class UpPolish(GeometryModule):
    r"""Polishes an up estimate on the image's straight edges (vanishing-point refinement).

    :class:`GravityHead` scores up on a coarse grid of candidates from coarse features,
    which finds the right neighbourhood but is several degrees off. Vertical lines pin up
    much more tightly: their great circles all run through it. Starting from the estimate
    :math:`\hat u`, the polish takes the ``topk`` strongest visible edges of the image
    (full resolution), their normalized structure tensors :math:`\hat T_m = T_m /
    \operatorname{tr} T_m` (:func:`structure_tensors`) and coherences :math:`c_m =
    \lambda_1 - \lambda_2` of :math:`\hat T_m` (1 for a straight edge, near 0 for a corner
    or a texture), and repeats, for :math:`\kappa` over ``kappas``,

    .. math::
        u \leftarrow \operatorname*{arg\,min}_{|u| = 1}\; u^\top \Big(\sum_m c_m^2
        e^{-\kappa e_m(u)} \hat T_m\Big) u, \qquad
        e_m(u) = \frac{u^\top \hat T_m u}{1 - (u \cdot p_m)^2},

    the eigenvector of the smallest eigenvalue, signed like the current u
    (:math:`e_m` is the squared sine of the angle between edge m's great circle and u).
    The rising :math:`\kappa` gives no weight to edges that run far from the current u
    (horizontal lines, textures), an iteratively reweighted least-squares fit. It has no
    parameters and no gradient (the estimate is trained through the head's scores), and
    it rotates with the input. Where the image has no such edges (the fit is
    degenerate) or the fit ends more than ``max_step`` radians from :math:`\hat u`, the
    estimate is kept. Edges weaker than ``min_strength`` (:math:`\operatorname{tr} T_m`,
    squared colour change per radian) are rounding noise and do not count. On the rooms
    protocol's new panoramas it takes the median error from 7.6 to 1.6 degrees (README).

    Shapes: ``x [B, N, C]`` (the image; hidden points are filled with their nearest
    visible value first, :class:`~usf_graph.nn.FillHidden`), ``mask [N]`` or
    ``None``, ``up [B, 3]`` -> ``[B, 3]``.
    """

    def __init__(self, grid, spacing: float, topk: int = 2048,
                 kappas=(20.0, 20.0, 50.0, 50.0, 200.0, 200.0, 800.0),
                 max_step: float = math.radians(30), min_strength: float = 1e-10):
        super().__init__()
        self.topk, self.kappas = topk, tuple(kappas)
        self.max_step, self.min_strength = max_step, min_strength
        self.fill = FillHidden(grid.pos)
        self.jet = SurfaceJet(grid.pos, *grid_graph(grid, 2.5 * spacing), spacing)
        self.register_buffer("pos", grid.pos.double(), persistent=False)

    @torch.no_grad()
    def forward(self, x: torch.Tensor, mask: torch.Tensor | None, up: torch.Tensor) -> torch.Tensor:
        """The polished estimate ``[B, 3]`` from the image ``x [B, N, C]``, ``mask`` and the
        estimate ``up [B, 3]``.
        """
        idx, T, tr, vis = strongest_edges(self.jet, self.fill(x, mask), mask, self.topk,
                                          self.min_strength)
        T = T.double() / tr.double().clamp_min(1e-300)[..., None, None]
        w = rank2_gap(T) * vis.double()
        p, u0 = self.pos[idx], up.double()
        u, ok = u0, torch.ones(len(up), dtype=torch.bool, device=up.device)
        for kappa in self.kappas:
            s2 = (1 - (p * u[:, None]).sum(-1) ** 2).clamp_min(1e-12)
            # a squared sine: >= 0 up to the rounding of T, which an edge at u would blow up
            e = (torch.einsum("bi,bkij,bj->bk", u, T, u) / s2).clamp_min(0)
            a = w * torch.exp(-kappa * e)
            # ONNX has no eigendecomposition: its export traces Jacobi rotations instead
            eigh = symmetric_eigh3 if torch.onnx.is_in_onnx_export() else torch.linalg.eigh
            val, vec = eigh(torch.einsum("bk,bkij->bij", a, T))
            # a fit is only defined with edges and a unique smallest eigenvalue
            ok = ok & (a.sum(-1) > 1e-9) & (val[:, 1] - val[:, 0] > 1e-9 * val[:, 2])
            new = vec[..., 0] * torch.where((vec[..., 0] * u).sum(-1, keepdim=True) < 0, -1.0, 1.0)
            u = torch.where(ok[:, None], new, u)
        ok = ok & ((u * u0).sum(-1) > math.cos(self.max_step))
        return torch.where(ok[:, None], u, u0).to(up.dtype)


def structure_tensors(jet: SurfaceJet, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    r"""Colour structure tensors :math:`T_m = \sum_c g_{mc} g_{mc}^\top` of ``x [B, N, C]``,
    the gradients :math:`g_{mc}` rebuilt in 3D from ``jet`` (a :class:`SurfaceJet` on the
    same grid) -> ``(T [B, N, 3, 3], trace [B, N])``."""
    frame = jet.frame.to(x.dtype)  # [N, 2, 3]
    d = jet(x)  # [B, N, C, 5]
    g = d[..., 0, None] * frame[:, None, 0] + d[..., 1, None] * frame[:, None, 1]
    T = torch.einsum("bnci,bncj->bnij", g, g)
    return T, T.diagonal(dim1=-2, dim2=-1).sum(-1)


def rank2_gap(T: torch.Tensor) -> torch.Tensor:
    r"""The squared gap :math:`(\lambda_2 - \lambda_1)^2 = 2 \operatorname{tr}(T^2) -
    \operatorname{tr}(T)^2` between the two eigenvalues of symmetric ``T [..., 3, 3]``
    whose third is 0, as a structure tensor of tangent gradients is; clamped at 0 against
    rounding. In closed form: CUDA's batched ``eigvalsh`` asked for a 16 GiB workspace for
    16 x 2048 such matrices (session 40)."""
    t = T.diagonal(dim1=-2, dim2=-1).sum(-1)
    return (2 * (T * T).sum((-2, -1)) - t * t).clamp_min(0)


def _jacobi_rotation(p: int, q: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The constant parts of a rotation in the (p, q) plane: ``J = I + (c - 1) D + s R``."""
    D, R = torch.zeros(3, 3, dtype=torch.float64), torch.zeros(3, 3, dtype=torch.float64)
    D[p, p] = D[q, q] = 1.0
    R[p, q], R[q, p] = 1.0, -1.0
    return D, R


_ROTATIONS = {pq: _jacobi_rotation(*pq) for pq in ((0, 1), (0, 2), (1, 2))}


def symmetric_eigh3(A: torch.Tensor, sweeps: int = 4) -> tuple[torch.Tensor, torch.Tensor]:
    r"""``torch.linalg.eigh`` of symmetric ``A [..., 3, 3]`` by cyclic Jacobi rotations:
    ``(values [..., 3] ascending, vectors [..., 3, 3] as columns)``. Each rotation zeroes
    one off-diagonal entry (:math:`t = \operatorname{sgn}\tau / (|\tau| + \sqrt{1 +
    \tau^2})`, :math:`\tau = (a_{qq} - a_{pp}) / 2 a_{pq}`); convergence is quadratic, and
    4 sweeps reach float64's precision on 3x3 matrices (repeated eigenvalues included).
    What the up polish runs while ``torch.onnx.export`` traces it: square roots and
    products only, which ONNX can hold, where it has no eigendecomposition."""
    eye = torch.eye(3, dtype=A.dtype, device=A.device)
    a, v = A, eye.expand_as(A)
    tiny = torch.finfo(A.dtype).tiny
    for _ in range(sweeps):
        for (p, q), (D, R) in _ROTATIONS.items():
            apq, app, aqq = a[..., p, q], a[..., p, p], a[..., q, q]
            zero = apq.abs() <= tiny
            tau = (aqq - app) / (2 * torch.where(zero, 1.0, apq))
            t = torch.where(zero, 0.0, torch.sign(tau) + (tau == 0)) / (tau.abs() + torch.sqrt(1 + tau * tau))
            c = torch.rsqrt(1 + t * t)
            J = eye + (c - 1)[..., None, None] * D.to(A) + (t * c)[..., None, None] * R.to(A)
            a = J.transpose(-1, -2) @ a @ J
            v = v @ J
    val, order = torch.sort(torch.diagonal(a, dim1=-2, dim2=-1), dim=-1)
    return val, torch.gather(v, -1, order[..., None, :].expand_as(v))


def strongest_edges(jet: SurfaceJet, x: torch.Tensor, mask: torch.Tensor | None, k: int,
                    min_strength: float | None = None):
    """The ``k`` strongest visible edges of ``x [B, N, C]`` (largest trace of their
    :func:`structure_tensors`; ``mask [N]`` or ``None``; with ``min_strength``, edges no
    stronger than it count as hidden) -> ``(index [B, K], T [B, K, 3, 3], trace [B, K],
    visible [B, K])``, ``visible`` 1 or 0 in x's dtype."""
    T, tr = structure_tensors(jet, x)
    vis = tr.new_ones(tr.shape) if min_strength is None else (tr > min_strength).to(tr.dtype)
    if mask is not None:
        vis = vis * mask.to(tr.dtype)
    idx = (tr * vis).topk(min(k, tr.shape[1]), dim=1).indices
    return (idx, T.gather(1, idx[..., None, None].expand(-1, -1, 3, 3)), tr.gather(1, idx),
            vis.gather(1, idx))


__all__ = ["UNSURE_MARGIN", "GravityHead", "EdgeVotes", "UpPolish", "heights", "pick_axis", "rank2_gap",
           "structure_tensors", "strongest_edges", "symmetric_eigh3"]
