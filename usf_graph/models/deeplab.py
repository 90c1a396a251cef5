r"""Spherical DeepLab v3: a spherical encoder, atrous spatial pyramid pooling made of
distance-kernel convolutions at several radii, and the v3+ decoder."""

from __future__ import annotations

import torch
from torch import nn

from ..nn import MaskedBatchNorm
from ..nn.pool import global_mean_pool_area
from .stages import ConvStage, _oriented, blur, level_spacing
from .unet import SphericalBackbone, _Segmenter
from .upnet import _check_upright


class Pointwise(nn.Module):
    """A per-point linear map -> masked BatchNorm -> ReLU (the 1x1 conv of planar nets)."""

    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.lin = nn.Linear(c_in, c_out, bias=False)
        self.norm = MaskedBatchNorm(c_out)

    def forward(self, x, mask=None, area=None):
        return torch.relu(self.norm(self.lin(x), mask=mask, node_weight=area))


class SphericalDeepLabV3(_Segmenter):
    r"""DeepLab v3 on the icosahedral hierarchy.

    * Encoder: a :class:`~usf_graph.models.unet.SphericalBackbone` from ``level`` down to
      ``aspp_level`` (default: one level per entry of ``channels``; no decoder).
    * ASPP on ``aspp_level``: a pointwise branch, :class:`ConvStage` branches whose kernel
      radii are ``rates`` grid spacings (the atrous rates: a distance kernel's support
      is its dilation), and image pooling (the area-weighted mean over the visible
      sphere, broadcast back), concatenated and fused pointwise.
    * Decoder (v3+): Gaussian upsampling to ``level``, concatenation with the first
      stage's features, a :class:`ConvStage` and a per-point linear map to logits.

    Every piece depends on distances only, so the logits are SO(3)-equivariant like
    :class:`~usf_graph.models.SphericalUNet`'s, whose ``gravity`` option (an
    :class:`~usf_graph.models.UpNet` whose estimate gives every point its height as one more
    input channel; ``forward(x, mask, up=...)`` takes a known up) and ``upright`` option
    (:class:`~usf_graph.nn.UpJet` features in the backbone) it shares. ``upright_convs`` (a
    level): the stages on that level and coarser, the ASPP's and the decoder's included,
    use :class:`~usf_graph.nn.UprightConv`, oriented kernels in the frame of up (None:
    none).

    Shapes: ``x [B, N, in_channels]`` on ``icosahedral(level + refine)``, optional
    ``mask [N]`` -> logits ``[B, N, num_classes]`` (and the gravity estimate with
    ``return_gravity``).
    """

    def __init__(self, num_classes: int = 13, in_channels: int = 3, level: int = 5,
                 aspp_level: int | None = None, channels=(32, 64, 128), aspp_channels: int = 128,
                 rates=(2, 4, 6), low_channels: int = 32, num_basis: int = 3,
                 radius_spacings: float = 3.0, jet_spacings: float = 3.5, pairs: int = 8,
                 pair_stages: int = 2, gravity: bool = False, refine: int = 0,
                 upright: bool = False, up_fields: int = 8, upright_convs: int | None = None,
                 gray: bool = False):
        super().__init__()
        aspp_level = level - len(channels) + 1 if aspp_level is None else aspp_level
        self.config = dict(num_classes=num_classes, in_channels=in_channels, level=level,
                           aspp_level=aspp_level, channels=list(channels),
                           aspp_channels=aspp_channels, rates=list(rates),
                           low_channels=low_channels, num_basis=num_basis,
                           radius_spacings=radius_spacings, jet_spacings=jet_spacings,
                           pairs=pairs, pair_stages=pair_stages, gravity=gravity, refine=refine,
                           upright=upright, up_fields=up_fields, upright_convs=upright_convs,
                           gray=gray)
        _check_upright(upright, gravity)
        self.backbone = SphericalBackbone(in_channels + int(gravity), level, aspp_level,
                                          aspp_level, channels, num_basis, radius_spacings,
                                          jet_spacings, pairs, pair_stages, refine, upright=upright, up_fields=up_fields,
                                          upright_convs=upright_convs)
        self.num_points = self.backbone.num_points
        ga, gl = self.backbone.grids[aspp_level], self.backbone.grids[level]
        c, a = self.backbone.out_channels, aspp_channels
        self.register_buffer("area_aspp", ga.area.float(), persistent=False)
        self.register_buffer("area_out", gl.area.float(), persistent=False)
        self.point = Pointwise(c, a)
        oriented = _oriented(aspp_level, upright_convs)
        self.atrous = nn.ModuleList([ConvStage(ga, c, a, r * level_spacing(aspp_level), num_basis,
                                               upright=oriented) for r in rates])
        self.image_pool = nn.Linear(c, a)
        self.fuse = Pointwise(a * (len(rates) + 2), a)
        self.up = blur(ga, gl, 0.5 * level_spacing(aspp_level))
        self.low = Pointwise(self.backbone.skip_channels[0], low_channels)
        self._gravity_net(gravity, in_channels, level, refine, gray)
        self.decoder = ConvStage(gl, a + low_channels, a // 2,
                                 radius_spacings * level_spacing(level), num_basis,
                                 upright=_oriented(level, upright_convs))
        self.head = nn.Linear(a // 2, num_classes)
        self.reset_parameters()

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None,
                up: torch.Tensor | None = None, return_gravity: bool = False):
        """Per-point logits ``[B, N, num_classes]``; arguments as
        :meth:`SphericalUNet.forward <usf_graph.models.SphericalUNet.forward>`.
        """
        x, grav, up = self._with_height(x, mask, up, return_gravity)
        feats = self.backbone.encode(x, mask, up)
        (low, m_low), (f, m) = feats[0], feats[-1]
        area = self.area_aspp.to(f.dtype)
        g = torch.relu(self.image_pool(global_mean_pool_area(f, area, m)))
        branches = [self.point(f, m, area)] + [s(f, m, up) for s in self.atrous]
        branches.append(g[:, None].expand(-1, f.shape[1], -1))
        y, _ = self.up(self.fuse(torch.cat(branches, -1), m, area), m)
        parts = [y, self.low(low, m_low, self.area_out.to(f.dtype))]
        logits = self.head(self.decoder(torch.cat(parts, -1), m_low, up))
        return (logits, grav) if return_gravity else logits


__all__ = ["SphericalDeepLabV3"]
