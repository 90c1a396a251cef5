"""How dense spherical models with an up estimate (``gravity=True``) are trained: the
network reads the heights along the views' known gravity, slightly jittered, while its
:class:`~usf_graph.models.UpNet` learns to estimate that gravity from the image."""

from __future__ import annotations

import torch

from ..geometry import geodesic_distance

#: Weight of the up estimate's loss (:meth:`GravityHead.loss`) in a training step.
UP_WEIGHT = 0.5
#: Noise (per axis) on the true up that the network reads in training, so that it learns
#: to tolerate the estimate's error at test time.
UP_JITTER = 0.05


def known_up(batch, n: int, dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """``(g, jittered g)``, each ``[n, 3]``: the batch's ``up`` when it has one, else +z
    (gravity-aligned views)."""
    g = getattr(batch, "up", None)
    g = torch.tensor([0.0, 0.0, 1.0]).expand(n, 3) if g is None else g.view(-1, 3)
    g = g.to(dtype)
    return g, g + UP_JITTER * torch.randn_like(g)


def up_loss(net, grav: dict, g: torch.Tensor, stats: dict) -> torch.Tensor:
    """``UP_WEIGHT`` times the up estimate's loss; records its mean error (degrees)."""
    stats["up_err_deg"] = float(torch.rad2deg(geodesic_distance(grav["up"].detach(), g)).mean())
    return UP_WEIGHT * net.gravity.head.loss(grav, g)


__all__ = ["UP_WEIGHT", "UP_JITTER", "known_up", "up_loss"]
