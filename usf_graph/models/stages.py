"""The building blocks of the dense spherical models (:mod:`~usf_graph.models.unet`,
:mod:`~usf_graph.models.deeplab`, :mod:`~usf_graph.models.detector`): grid spacings, mask-aware
conv stages, Gaussian resampling between levels and the input check."""

from __future__ import annotations

import math

import torch
from torch import nn

from ..frontend import grid_graph
from ..grids import icosahedral
from ..nn import GaussianPool, MaskedBatchNorm, SphericalConv, UprightConv
from ..nn.precision import GeometryModule
from ..tracing import check_values, field_of

_SPACING: dict[int, float] = {}


def level_spacing(level: int) -> float:
    """Mean spacing (radians) of ``icosahedral(level)``, memoized."""
    if level not in _SPACING:
        _SPACING[level] = float(icosahedral(level).spacing)
    return _SPACING[level]


class ConvStage(GeometryModule):
    """``depth`` times conv -> masked BatchNorm -> ReLU on one grid (area-weighted,
    mask-aware); ``radius`` in radians (at most pi: the whole sphere). ``upright``:
    :class:`~usf_graph.nn.UprightConv` instead of :class:`~usf_graph.nn.SphericalConv`,
    and ``forward(x, mask, up)`` needs the unit ``up [B, 3]``."""

    def __init__(self, grid, c_in: int, c_out: int, radius: float, num_basis: int,
                 depth: int = 1, upright: bool = False):
        super().__init__()
        radius = min(radius, math.pi)
        ei, ew = grid_graph(grid, radius)
        self.register_buffer("area", grid.area.float(), persistent=False)
        self.upright = upright
        self.convs, self.norms = nn.ModuleList(), nn.ModuleList()
        for k in range(depth):
            conv = (UprightConv if upright else SphericalConv)(
                c_in if k == 0 else c_out, c_out, radius, num_basis=num_basis, basis="gaussian")
            extra = {"pos": grid.pos} if upright else {}
            self.convs.append(conv.bind(ei, ew.float(), node_weight=self.area, **extra))
            self.norms.append(MaskedBatchNorm(c_out))

    def forward(self, x, mask=None, up=None):
        a = self.area.to(x.dtype)
        for conv, norm in zip(self.convs, self.norms):
            y = conv(x, up, mask=mask) if self.upright else conv(x, mask=mask)
            x = torch.relu(norm(y, mask=mask, node_weight=a))
        return x


def refined_copy(module: nn.Module, levels: int) -> nn.Module:
    """``module`` (built from its ``config``, with a ``refine`` entry) rebuilt for inputs
    ``levels`` grid levels finer, with its weights, device, dtype and mode: every radius is
    in radians, so the same weights apply."""
    new = type(module)(**{**module.config, "refine": module.config.get("refine", 0) + levels})
    p = next(module.parameters())
    new = new.to(device=p.device, dtype=p.dtype)
    new.load_state_dict(module.state_dict())
    return new.train(module.training)


def _oriented(level: int, upright_convs: int | None) -> bool:
    """Whether a stage on ``level`` uses :class:`~usf_graph.nn.UprightConv`: on levels up to
    ``upright_convs`` (None: none)."""
    return upright_convs is not None and level <= upright_convs


def blur(src, dst, sigma: float) -> GaussianPool:
    """Gaussian resampling from grid ``src`` to grid ``dst`` (pooling or upsampling),
    ``sigma`` in radians."""
    return GaussianPool(src.pos, dst.pos, sigma, area=src.area)


def check_input(x: torch.Tensor, mask, n: int, c: int, level: int):
    """Validate ``x [B, n, c]`` and ``mask [n]``; returns the mask as bool, or ``None``
    when everything is seen."""
    if x.dim() != 3 or tuple(x.shape[1:]) != (n, c):
        raise ValueError(f"expected x [B, {n}, {c}] (a signal on icosahedral:{level}), got "
                         f"{tuple(x.shape)}")
    if check_values() and not torch.isfinite(x).all():
        raise ValueError("x has NaN or inf; lift images with SphericalFrontend or clean them")
    if mask is None:
        return None
    seen = field_of(mask) if mask.shape == (n,) else None
    if seen is None or not seen.any():
        raise ValueError(f"mask must be a bool [{n}] with some point visible, got "
                         f"{tuple(mask.shape)}")
    return None if seen.all() else mask.bool()


__all__ = ["level_spacing", "ConvStage", "blur", "check_input", "refined_copy"]
