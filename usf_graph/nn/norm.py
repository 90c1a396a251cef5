"""Normalization over the visible points of ``[N, C]`` or ``[B, N, C]`` signals."""

from __future__ import annotations

import torch
from torch import nn

from .batching import check_per_point


class MaskedBatchNorm(nn.Module):
    r"""Batch normalization whose statistics use only visible points (``mask``), weighted
    by ``node_weight`` (areas) when given, with running statistics for evaluation.

    Per channel, :math:`\mu = \sum w_j x_j / \sum w_j`, :math:`\sigma^2` likewise, over
    the batch and the visible points; hidden points are passed through normalized with the
    same statistics. Rotating the signal permutes points and so leaves the statistics
    unchanged on a grid symmetric under the rotation.

    The statistics pool every visible point of every sample, as torch's BatchNorm does,
    so a PyG batch ``[sum N_i, C]`` (graphs of any sizes; ``mask`` and ``node_weight``
    per point, ``batch`` accepted for a uniform call) gives the same result as the static
    form ``[B, N, C]`` of the same samples (``mask`` ``[N]`` or ``[B, N]``), and in
    evaluation mode the same as each graph alone.

    Shapes: ``[N, C]``, ``[B, N, C]`` or ``[sum N_i, C]`` -> same.
    """

    def __init__(self, channels: int, eps: float = 1e-5, momentum: float = 0.1):
        super().__init__()
        self.channels, self.eps, self.momentum = channels, eps, momentum
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))
        self.register_buffer("running_mean", torch.zeros(channels))
        self.register_buffer("running_var", torch.ones(channels))

    def reset_parameters(self) -> None:
        """Scale 1, shift 0, running mean 0 and variance 1."""
        nn.init.ones_(self.weight)
        nn.init.zeros_(self.bias)
        self.running_mean.zero_()
        self.running_var.fill_(1)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None,
                node_weight: torch.Tensor | None = None,
                batch: torch.Tensor | None = None) -> torch.Tensor:
        """``x`` normalized with statistics over its visible points (weighted by
        ``node_weight``) in training, with the running statistics in evaluation.
        """
        if x.dim() not in (2, 3) or x.shape[-1] != self.channels:
            raise ValueError(f"x must be [N, {self.channels}], [B, N, {self.channels}] or a "
                             f"PyG batch [sum N_i, {self.channels}], got {tuple(x.shape)}")
        N = x.shape[-2]
        if batch is not None and (x.dim() != 2 or batch.shape != (N,)):
            raise ValueError(f"batch must be [sum N_i] for x [sum N_i, C], got batch "
                             f"{tuple(batch.shape)} and x {tuple(x.shape)}")
        check_per_point("mask", mask, N, x.dim() - 1)
        check_per_point("node_weight", node_weight, N, x.dim() - 1)
        if self.training:
            w = torch.ones(N, dtype=x.dtype, device=x.device) if node_weight is None \
                else node_weight.to(x.dtype)
            if mask is not None:
                w = w * mask.to(x.dtype)
            # weighted sums as matrix-vector products: no [B, N, C] temporaries for x * w
            w = w.expand(x.shape[:-1]).reshape(-1)
            w = w / w.sum().clamp_min(1e-30)
            flat = x.reshape(-1, x.shape[-1])
            mean = w @ flat
            xc = flat - mean
            var = w @ (xc * xc)
            with torch.no_grad():
                self.running_mean.lerp_(mean.detach().to(self.running_mean.dtype), self.momentum)
                self.running_var.lerp_(var.detach().to(self.running_var.dtype), self.momentum)
            scale = self.weight * torch.rsqrt(var + self.eps)
            return torch.addcmul(self.bias, xc, scale).view_as(x)
        mean, var = self.running_mean.to(x.dtype), self.running_var.to(x.dtype)
        scale = self.weight * torch.rsqrt(var + self.eps)
        return torch.addcmul(self.bias - mean * scale, x, scale)

    def extra_repr(self) -> str:
        return f"{self.channels}, eps={self.eps}, momentum={self.momentum}"
