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

from ..geometry import geodesic_distance
from ..grids import icosahedral


def heights(pos: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    """``p . up`` for points ``pos [N, 3]`` and directions ``up [B, 3]`` -> ``[B, N, 1]``."""
    return (pos.to(up.dtype) @ up.T).T[..., None]


class GravityHead(nn.Module):
    r"""Estimates the up direction of a spherical image, SO(3)-equivariantly.

    Every candidate direction :math:`a_n` (the points of ``icosahedral(candidate_level)``)
    gets a score from the coarse features :math:`f_m` at points :math:`p_m`,

    .. math::
        U_n = \frac{\sum_m w_m \sum_k \varphi_k(\theta_{nm})\, W_k f_m}{\sum_m w_m},
        \qquad s_n = v^\top \mathrm{ReLU}(U_n + b),

    with :math:`\theta_{nm}` the geodesic distance from :math:`a_n` to :math:`p_m`,
    ``num_basis`` Gaussian bumps :math:`\varphi_k` over :math:`[0, \pi]`, and :math:`w` the
    grid's areas inside the field of view. This is a distance-kernel convolution with a
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

    Shapes: features ``[B, M, C]`` on ``coarse``, ``mask [M]`` or ``None`` ->
    ``{"up": [B, 3], "logits": [B, Nc], "height": [B, M], "weight": [M]}`` (``weight``: the
    visible areas).
    """

    def __init__(self, coarse, channels: int, hidden: int = 32, num_basis: int = 8,
                 candidate_level: int = 3, window: float = math.radians(20),
                 concentration: float = 100.0):
        super().__init__()
        self.hidden, self.num_basis = hidden, num_basis
        self.window, self.concentration = window, concentration
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
        self.field.reset_parameters()
        self.height.reset_parameters()
        self.score.reset_parameters()
        nn.init.zeros_(self.bias)

    def forward(self, f: torch.Tensor, mask: torch.Tensor | None = None) -> dict:
        B, M, _ = f.shape
        w = self.area.to(f.dtype) * (1 if mask is None else mask.to(f.dtype))
        z = self.field(f).view(B, M, self.num_basis, self.hidden) * (w / w.sum())[:, None, None]
        U = torch.einsum("knm,bmkh->bnh", self.phi.to(f.dtype), z)
        logits = self.score(torch.relu(U + self.bias))[..., 0]  # [B, Nc]
        cand = self.candidates.to(f.dtype)
        best = cand[logits.argmax(-1)]  # [B, 3]
        near = best @ cand.T > math.cos(self.window)
        p = torch.softmax(logits.masked_fill(~near, float("-inf")), -1)
        up = p @ cand
        return {"up": up / up.norm(dim=-1, keepdim=True).clamp_min(1e-12), "logits": logits,
                "height": self.height(f)[..., 0], "weight": w}

    def target(self, g: torch.Tensor) -> torch.Tensor:
        r"""The distribution over candidates the scores are trained towards for the true up
        ``g [B, 3]``: :math:`q_n \propto \exp(\kappa\, a_n \cdot g)` (``concentration``
        :math:`\kappa`; 100 is about 6 degrees wide) -> ``[B, Nc]``."""
        return torch.softmax(self.concentration * g @ self.candidates.to(g.dtype).T, -1)

    def loss(self, out: dict, g: torch.Tensor) -> torch.Tensor:
        """Cross-entropy of the scores (:meth:`forward`'s ``out``) against :meth:`target`,
        plus (when ``out`` has ``height``) the area-weighted squared error of the heights
        over the visible points."""
        logits = out["logits"]
        g = g.to(logits.dtype)
        q = self.target(g)
        ce = -(q * torch.log_softmax(logits, -1)).sum(-1).mean()
        if "height" not in out:
            return ce
        w = out["weight"]
        h = heights(self.pos, g)[..., 0]
        return ce + ((out["height"] - h) ** 2 * w).sum(-1).mean() / w.sum()


__all__ = ["GravityHead", "heights"]
