"""Normalization over the visible points of ``[N, C]`` or ``[B, N, C]`` signals."""

from __future__ import annotations

import torch
from torch import nn


class MaskedBatchNorm(nn.Module):
    r"""Batch normalization whose statistics use only visible points (``mask``), weighted
    by ``node_weight`` (areas) when given, with running statistics for evaluation.

    Per channel, :math:`\mu = \sum w_j x_j / \sum w_j`, :math:`\sigma^2` likewise, over
    the batch and the visible points; hidden points are passed through normalized with the
    same statistics. Rotating the signal permutes points and so leaves the statistics
    unchanged on a grid symmetric under the rotation.

    Shapes: ``[N, C]`` or ``[B, N, C]`` -> same.
    """

    def __init__(self, channels: int, eps: float = 1e-5, momentum: float = 0.1):
        super().__init__()
        self.channels, self.eps, self.momentum = channels, eps, momentum
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))
        self.register_buffer("running_mean", torch.zeros(channels))
        self.register_buffer("running_var", torch.ones(channels))

    def reset_parameters(self) -> None:
        nn.init.ones_(self.weight)
        nn.init.zeros_(self.bias)
        self.running_mean.zero_()
        self.running_var.fill_(1)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None,
                node_weight: torch.Tensor | None = None) -> torch.Tensor:
        if self.training:
            N = x.shape[-2]
            w = torch.ones(N, dtype=x.dtype, device=x.device) if node_weight is None \
                else node_weight.to(x.dtype)
            if mask is not None:
                w = w * mask.to(x.dtype)
            w = w[:, None] / (w.sum() * (x.shape[0] if x.dim() == 3 else 1))
            dims = tuple(range(x.dim() - 1))
            mean = (x * w).sum(dims)
            var = (((x - mean) ** 2) * w).sum(dims)
            with torch.no_grad():
                self.running_mean.lerp_(mean.detach().to(self.running_mean.dtype), self.momentum)
                self.running_var.lerp_(var.detach().to(self.running_var.dtype), self.momentum)
        else:
            mean, var = self.running_mean.to(x.dtype), self.running_var.to(x.dtype)
        return (x - mean) / torch.sqrt(var + self.eps) * self.weight + self.bias

    def extra_repr(self) -> str:
        return f"{self.channels}, eps={self.eps}, momentum={self.momentum}"
