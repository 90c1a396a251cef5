"""DistanceKernel: K basis functions of a distance, shared by S2 (geodesic) and R3."""

from __future__ import annotations

import math

import torch
from torch import nn

BASES = ("hat", "gaussian", "bessel", "mlp")


def envelope(x: torch.Tensor) -> torch.Tensor:
    """C2 cutoff 1 - 10x^3 + 15x^4 - 6x^5 on [0, 1]: 1 at 0, 0 (with zero slope) at 1.

    Never negative: near 1 the polynomial rounds below 0 (to -8e-7 in float32), and a
    normalization that divides by those values (:class:`~usf_graph.nn.DistanceConv` at a
    point seeing only its kernel's rim) would blow up."""
    x = x.clamp(0, 1)
    return (1 - x ** 3 * (10 - 15 * x + 6 * x * x)).clamp_min(0)


class DistanceKernel(nn.Module):
    r"""Maps distances :math:`d \in [0, r]` to :math:`K` basis values :math:`\phi_k(d)`.

    Bases:
        * ``hat``: linear hat functions centred at :math:`c_k = k r / K`, width
          :math:`r / K`; they sum to 1 up to the last centre and fall linearly to 0 at r.
        * ``gaussian``: :math:`\exp(-(d - c_k)^2 / 2\sigma^2)`, :math:`c_k` evenly in
          [0, r], :math:`\sigma = r / K`, times a smooth envelope.
        * ``bessel``: :math:`\sqrt{2/r}\,\sin(k\pi d / r) / d` (finite at d = 0), times the
          envelope.
        * ``mlp``: a small learnable MLP of :math:`d / r` with K outputs, times the envelope.

    Every basis is 0 for :math:`d \geq r`, so a point crossing the radius changes a
    convolution continuously. Distances depend only on the geometry, hence the same
    kernel serves geodesic distances on S2 and euclidean distances in R3.

    Shapes:
        - input: ``d [E]``
        - output: ``[E, K]``
    """

    def __init__(self, num_basis: int, cutoff: float, basis: str = "hat", hidden: int = 16):
        super().__init__()
        if basis not in BASES:
            raise ValueError(f"unknown basis {basis!r}; use one of {BASES}")
        if num_basis < 1 or not cutoff > 0:
            raise ValueError(f"need num_basis >= 1 and cutoff > 0, got {num_basis}, {cutoff}")
        self.num_basis, self.cutoff, self.basis = int(num_basis), float(cutoff), basis
        self.mlp = nn.Sequential(nn.Linear(1, hidden), nn.SiLU(), nn.Linear(hidden, num_basis)) \
            if basis == "mlp" else None

    @property
    def learnable(self) -> bool:
        """True for the ``mlp`` basis, whose values depend on parameters (no caching)."""
        return self.mlp is not None

    @property
    def positive(self) -> bool:
        """Whether every basis function is >= 0 (``hat``, ``gaussian``)."""
        return self.basis in ("hat", "gaussian")

    def reset_parameters(self) -> None:
        """Re-initializes the MLP basis (the fixed bases have no parameters)."""
        if self.mlp is not None:
            for m in self.mlp:
                if isinstance(m, nn.Linear):
                    m.reset_parameters()

    def forward(self, d: torch.Tensor) -> torch.Tensor:
        """The K basis values ``[E, K]`` at distances ``d [E]`` (0 at and past the cutoff)."""
        r, K = self.cutoff, self.num_basis
        x = (d / r)[:, None]
        inside = (x < 1).to(d.dtype)
        k = torch.arange(K, dtype=d.dtype, device=d.device)
        if self.basis == "hat":
            return torch.relu(1 - (x * K - k).abs()) * inside
        if self.basis == "gaussian":
            c = k / max(K - 1, 1)
            out = torch.exp(-0.5 * ((x - c) * K) ** 2)
        elif self.basis == "bessel":
            n = k + 1
            out = math.sqrt(2 / r) * (n * math.pi / r) * torch.sinc(n * x)
        else:
            out = self.mlp(x)
        return out * envelope(x) * inside

    def __repr__(self) -> str:
        return f"{type(self).__name__}(num_basis={self.num_basis}, cutoff={self.cutoff:.4g}, basis='{self.basis}')"
