r"""The spherical U-Net: a mask-aware encoder-decoder on the icosahedral hierarchy.

:class:`SphericalBackbone` is shared by the segmentation models and the detector; it holds
the pieces every dense spherical model needs: the invariant local features of the input
(:class:`~usf_graph.nn.LocalJet`, :class:`~usf_graph.nn.GradientPairs`), conv stages that
see only the camera's field of view, Gaussian pooling and upsampling between levels, and
skip connections.

**Resolution transfer.** Every radius (kernels, jet fits, pooling blurs) is fixed in
radians from the grid levels the model was built for; ``refine=k`` runs the same network
on grids ``k`` levels finer. A distance-kernel convolution with area weights is a
quadrature of one continuous operator, so the refined network computes (a better
approximation of) the same function and takes the trained weights unchanged
(:meth:`SphericalUNet.refined`).
"""

from __future__ import annotations

import torch
from torch import nn

from ..frontend import grid_graph
from ..grids import icosahedral
from ..nn import (
    FillHidden,
    GradientPairs,
    LocalJet,
    MaskedBatchNorm,
    UpJet,
)
from ..nn.precision import GeometryModule
from .stages import ConvStage, _oriented, blur, check_input, level_spacing, refined_copy
from .upnet import UpNet, WithUp, _check_upright


class SphericalBackbone(GeometryModule):
    r"""Jet features, conv stages down from ``input_level`` to ``min_level`` and back up
    to ``out_level`` with skips.

    Stage s works on level ``input_level - s``: :class:`ConvStage` (``depth`` convolutions of
    kernel radius ``radius_spacings`` grid spacings), followed for the first ``pair_stages`` stages by
    ``pairs`` :class:`GradientPairs` (0: none) and, when ``upright``, an :class:`UpJet` of
    ``up_fields`` learned fields; Gaussian pooling (0.5 coarse spacings) between
    levels. The decoder upsamples with the same Gaussian, concatenates the skip and runs
    a :class:`ConvStage`. ``mask`` (one ``[N]`` for the batch) keeps hidden points out of
    every convolution and normalization; the jet and the gradient pairs see their inputs
    extended by the nearest visible values (:class:`FillHidden`), so the border of the
    field of view is not an edge.

    ``upright``: the backbone also reads a unit ``up [B, 3]`` (``encode(x, mask, up)``), a
    known gravity or an equivariant estimate: the :class:`UpJet` of the input and of the
    learned fields give it the orientation of edges relative to up, which distance-only
    kernels cannot see. The features stay invariant when up rotates with the input.
    ``upright_convs``: the stages on that level and coarser (encoder and decoder) use
    :class:`~usf_graph.nn.UprightConv`, whose kernels see the direction of each neighbour
    relative to up, as a planar CNN's filters see rows and columns (None: none).

    :meth:`encode` returns the ``(features, mask)`` of every level, :meth:`forward` the
    decoder's output ``([B, M, out_channels], mask [M] or None)`` on ``out_level``.
    """

    def __init__(self, in_channels: int = 3, input_level: int = 5, out_level: int = 5,
                 min_level: int = 2, channels=(32, 64, 128, 128), num_basis: int = 3,
                 radius_spacings: float = 3.0, jet_spacings: float = 3.5, pairs: int = 8,
                 pair_stages: int = 2, refine: int = 0, depth: int = 1, upright: bool = False,
                 up_fields: int = 8, upright_convs: int | None = None):
        super().__init__()
        if upright_convs is not None and not upright:
            raise ValueError("upright_convs reads up: it needs upright=True")
        if not min_level <= out_level <= input_level:
            raise ValueError(f"need min_level <= out_level <= input_level, got {min_level}, "
                             f"{out_level}, {input_level}")
        if len(channels) != input_level - min_level + 1:
            raise ValueError(f"channels needs one entry per level {input_level}..{min_level} "
                             f"({input_level - min_level + 1}), got {len(channels)}")
        if refine < 0:
            raise ValueError(f"refine must be >= 0, got {refine}")
        self.input_level, self.out_level, self.refine = input_level, out_level, refine
        self.grids = {lv: icosahedral(lv + refine) for lv in range(min_level, input_level + 1)}
        h = {lv: level_spacing(lv) for lv in self.grids}  # radii stay those of the base levels
        g = self.grids[input_level]
        self.num_points, self.in_channels = len(g), in_channels
        self.fill = FillHidden(g.pos)
        graph = grid_graph(g, jet_spacings * h[input_level])
        self.jet = LocalJet(g.pos, *graph, h[input_level])
        self.upright = upright
        self.up_jet = UpJet(g.pos, *graph, h[input_level], in_channels) if upright else None
        c_in, skips = (4 + 5 * upright) * in_channels, []
        self.jet_norm = MaskedBatchNorm(c_in)
        self.register_buffer("area_in", g.area.float(), persistent=False)
        self.down, self.pairs, self.pools = nn.ModuleList(), nn.ModuleList(), nn.ModuleList()
        self.fills, self.up_pairs = nn.ModuleList(), nn.ModuleList()
        for s, lv in enumerate(range(input_level, min_level - 1, -1)):
            g, c = self.grids[lv], channels[s]
            self.down.append(ConvStage(g, c_in, c, radius_spacings * h[lv], num_basis, depth,
                                       _oriented(lv, upright_convs)))
            c_in = c
            if s < pair_stages and lv > min_level and (pairs or upright and up_fields):
                graph = grid_graph(g, jet_spacings * h[lv])
                self.fills.append(FillHidden(g.pos))
                if pairs:
                    self.pairs.append(GradientPairs(g.pos, *graph, h[lv], c, pairs))
                    c_in += 2 * pairs
                if upright and up_fields:
                    self.up_pairs.append(UpJet(g.pos, *graph, h[lv], c, up_fields))
                    c_in += 5 * up_fields
            skips.append(c_in)
            if lv > min_level:
                self.pools.append(blur(g, self.grids[lv - 1], 0.5 * h[lv - 1]))
        self.skip_channels = skips
        self.ups, self.up = nn.ModuleList(), nn.ModuleList()
        for lv in range(min_level + 1, out_level + 1):
            skip = skips[input_level - lv]
            self.ups.append(blur(self.grids[lv - 1], self.grids[lv], 0.5 * h[lv - 1]))
            self.up.append(ConvStage(self.grids[lv], c_in + skip, skip, radius_spacings * h[lv],
                                     num_basis, depth, _oriented(lv, upright_convs)))
            c_in = skip
        self.out_channels = c_in

    def encode(self, x: torch.Tensor, mask: torch.Tensor | None = None,
               up: torch.Tensor | None = None) -> list:
        """``x [B, N, C]`` -> ``[(features, mask), ...]`` from ``input_level`` down; ``up
        [B, 3]`` (unit) is needed, and read, by an ``upright`` backbone only."""
        m = check_input(x, mask, self.num_points, self.in_channels, self.input_level + self.refine)
        if self.upright != (up is not None):
            raise ValueError("an upright backbone needs up [B, 3], and only it reads one")
        x = self.fill(x, m)
        x = self.jet(x) if up is None else torch.cat([self.jet(x), self.up_jet(x, up)], -1)
        x = self.jet_norm(x, mask=m, node_weight=self.area_in.to(x.dtype))
        feats = []
        for s, stage in enumerate(self.down):
            x = stage(x, m, up)
            if s < len(self.fills):
                xf, parts = self.fills[s](x, m), [x]
                if self.pairs:
                    parts.append(self.pairs[s](xf))
                if self.up_pairs:
                    parts.append(self.up_pairs[s](xf, up))
                x = torch.cat(parts, -1)
            feats.append((x, m))
            if s < len(self.pools):
                x, mp = self.pools[s](x, m)
                m = None if m is None else mp
        return feats

    def decode(self, feats: list, up: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Decoder over :meth:`encode`'s output (``up``: as for :meth:`encode`)."""
        feats = list(feats)
        x, m = feats.pop()
        for ups, stage in zip(self.ups, self.up):
            x, _ = ups(x, m)  # hidden coarse points hold no signal: keep them out
            skip, m = feats.pop()
            x = stage(torch.cat([x, skip], -1), m, up)
        return x, m

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None,
                up: torch.Tensor | None = None):
        """Encoder then decoder: ``([B, M, out_channels], mask [M] or None)`` on ``out_level``,
        for ``x [B, N, C]``, optional ``mask [N]`` and ``up [B, 3]`` (needed when ``upright``).
        """
        return self.decode(self.encode(x, mask, up), up)


class _Segmenter(WithUp):
    """What the segmentation models share: config round trip, resolution transfer and the
    optional up estimate (:class:`WithUp`; ``forward(x, mask, up=None,
    return_gravity=False)``, ``return_gravity=True`` also returning the estimate)."""

    config: dict

    def reset_parameters(self) -> None:
        for m in self.modules():
            if m is not self and hasattr(m, "reset_parameters"):
                m.reset_parameters()

    @classmethod
    def from_config(cls, config: dict):
        return cls(**config)

    def refined(self, levels: int = 1):
        """The same network on grids ``levels`` finer (module docstring), with these
        weights: for inputs lifted to ``icosahedral(level + levels)``."""
        net = refined_copy(self, levels)
        for old, new in zip(self.modules(), net.modules()):  # settings outside the state
            if hasattr(old, "gray"):  # read_gray's flags are not in the config
                new.gray = old.gray
            if isinstance(old, UpNet):
                new.level_prior = old.level_prior
                new.set_sign_check(None if old.sign_check is None else old.sign_check.refined(levels))
        return net


class SphericalUNet(_Segmenter):
    r"""Semantic segmentation on the sphere: a :class:`SphericalBackbone` from
    ``level`` down to ``min_level`` (default: one level per entry of ``channels``) and
    back, then ``head_depth`` conv stages on the finest level (0: none) and a per-point
    linear map to class logits.

    Every layer is a function of geodesic distances (or of rotation-invariant jet
    features), so the logits are SO(3)-equivariant: exactly for rotations that map the
    grid onto itself, up to discretization for any other.

    With ``gravity=True`` (what ``usf-graph train seg`` builds), a small :class:`UpNet`
    estimates up from the image, and the network reads each point's height along it as
    one more input channel (the cue "ceiling above, floor below" that a planar network
    reads from its rows); the logits stay equivariant, since the estimate rotates with
    the input. Training needs views of known gravity (:func:`~usf_graph.train.seg.segmentation_step`);
    ``forward(x, mask, up=...)`` takes a known up instead of the estimate. With
    ``upright=True`` as well, the backbone also reads the orientation of the input and of
    ``up_fields`` learned fields relative to up (:class:`~usf_graph.nn.UpJet`, see
    :class:`SphericalBackbone`), and ``upright_convs`` (a level) makes the stages on that
    level and coarser use :class:`~usf_graph.nn.UprightConv`. ``gray``: it reads only its
    input's luma, for mono cameras (:class:`WithUp`).

    Shapes: ``x [B, N, in_channels]`` on ``icosahedral(level + refine)``, optional
    ``mask [N]`` (the camera's field of view) -> logits ``[B, N, num_classes]`` (and the
    gravity estimate with ``return_gravity=True``, ``None`` without ``gravity``).
    """

    def __init__(self, num_classes: int = 13, in_channels: int = 3, level: int = 5,
                 min_level: int | None = None, channels=(32, 64, 128, 128), num_basis: int = 3,
                 radius_spacings: float = 3.0, jet_spacings: float = 3.5, pairs: int = 8,
                 pair_stages: int = 2, gravity: bool = False, depth: int = 1,
                 head_depth: int = 0, refine: int = 0, upright: bool = False, up_fields: int = 8,
                 upright_convs: int | None = None, gray: bool = False):
        super().__init__()
        min_level = level - len(channels) + 1 if min_level is None else min_level
        self.config = dict(num_classes=num_classes, in_channels=in_channels, level=level,
                           min_level=min_level, channels=list(channels), num_basis=num_basis,
                           radius_spacings=radius_spacings, jet_spacings=jet_spacings,
                           pairs=pairs, pair_stages=pair_stages, gravity=gravity, depth=depth,
                           head_depth=head_depth, refine=refine, upright=upright, up_fields=up_fields,
                           upright_convs=upright_convs, gray=gray)
        _check_upright(upright, gravity)
        self.backbone = SphericalBackbone(in_channels + int(gravity), level, level, min_level,
                                          channels, num_basis, radius_spacings, jet_spacings,
                                          pairs, pair_stages, refine, depth, upright, up_fields,
                                          upright_convs)
        c = self.backbone.out_channels
        self._gravity_net(gravity, in_channels, level, refine, gray)
        self.head_stage = ConvStage(self.backbone.grids[level], c, c,
                                    radius_spacings * level_spacing(level), num_basis,
                                    head_depth, _oriented(level, upright_convs)) if head_depth else None
        self.head = nn.Linear(c, num_classes)
        self.num_points = self.backbone.num_points
        self.reset_parameters()

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None,
                up: torch.Tensor | None = None, return_gravity: bool = False):
        """Per-point logits ``[B, N, num_classes]`` for ``x [B, N, in_channels]``; ``mask [N]``
        the camera's field of view, ``up [B, 3]`` a known gravity (else the estimate),
        ``return_gravity``: also return the estimate's dict (None without ``gravity``).
        """
        x, grav, up = self._with_height(x, mask, up, return_gravity)
        f, m = self.backbone(x, mask, up)
        logits = self.head(f if self.head_stage is None else self.head_stage(f, m, up))
        return (logits, grav) if return_gravity else logits


__all__ = ["SphericalBackbone", "SphericalUNet", "ConvStage", "blur", "FillHidden", "level_spacing"]
