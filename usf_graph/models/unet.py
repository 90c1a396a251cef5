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

import math

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
from ..nn.colour import check_gray, grayscale
from ..nn.precision import GeometryModule
from ..tracing import check_values
from .gravity import EdgeVotes, GravityHead, UpPolish, heights, level_scores
from .stages import ConvStage, _oriented, blur, check_input, level_spacing, refined_copy


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


class UpNet(GeometryModule):
    r"""The image's up direction, estimated SO(3)-equivariantly at low resolution.

    The input is pooled ``coarsen`` levels down (Gaussian, mask-aware), extended past the field of
    view (:class:`FillHidden`), described by its :class:`~usf_graph.nn.LocalJet`, passed
    through one :class:`ConvStage` per entry of ``channels`` on successively coarser levels,
    and read by a :class:`GravityHead`, whose scores get the :class:`EdgeVotes` of the
    pooled image's edges (``edge_votes``), weighted from the first stage's input and output.
    With ``polish``, the estimate is then fitted to the straight edges of the input at
    full resolution in evaluation mode (:class:`UpPolish`; ``"up_head"`` keeps the head's
    own; in training, where only the head's scores are trained, it is not run).
    It is small and separate from the segmenter, so that the segmenter's first layer can
    already read each point's height.

    **A level camera** (``level_prior`` :math:`\beta`, 0 by default; set it on a trained
    model with :func:`set_level_prior`). A camera mounted with its optical axis horizontal
    (most robots, cars, tripods) has up perpendicular to that axis. Without an IMU,
    :math:`\beta > 0` adds :func:`~usf_graph.models.gravity.level_scores` of the input's
    field of view to the head's scores: about :math:`\beta` against directions along a
    pinhole's axis, half that for a fisheye, nothing for a whole panorama. The field of view
    rotates with the camera, so the estimate stays equivariant; but the prior is wrong for a
    tilted narrow camera (one looking at the floor): leave it 0 there.

    ``gray``: it reads only the input's luma (:func:`~usf_graph.nn.colour.grayscale`).

    Shapes: ``x [B, N, in_channels]`` on ``icosahedral(level + refine)``, ``mask [N]`` or
    ``None`` -> :class:`GravityHead`'s output ``{"up": [B, 3], "logits": [B, Nc], ...}``.
    """

    def __init__(self, in_channels: int, level: int, channels=(32, 64, 128), num_basis: int = 3,
                 radius_spacings: float = 3.0, jet_spacings: float = 3.5, refine: int = 0,
                 coarsen: int = 1, edge_votes: bool = True, polish: bool = True,
                 gray: bool = False):
        super().__init__()
        self.gray = check_gray(gray, in_channels)
        levels = list(range(level - coarsen, level - coarsen - len(channels), -1))
        if not channels or coarsen < 0 or levels[-1] < 0:
            raise ValueError(f"UpNet needs coarsen >= 0 and 1 to {level - coarsen + 1} channel "
                             f"entries, got {coarsen} and {len(channels)}")
        grids = {lv: icosahedral(lv + refine) for lv in {level, *levels}}
        h = {lv: level_spacing(lv) for lv in grids}
        top = grids[levels[0]]
        self.pre = blur(grids[level], top, 0.5 * h[levels[0]]) if coarsen else None
        self.pools = nn.ModuleList([blur(grids[lv + 1], grids[lv], 0.5 * h[lv]) for lv in levels[1:]])
        self.fill = FillHidden(top.pos)
        self.jet = LocalJet(top.pos, *grid_graph(top, jet_spacings * h[levels[0]]), h[levels[0]])
        self.jet_norm = MaskedBatchNorm(4 * in_channels)
        self.register_buffer("area", top.area.float(), persistent=False)
        c_in, self.stages = 4 * in_channels, nn.ModuleList()
        for lv, c in zip(levels, channels):
            self.stages.append(ConvStage(grids[lv], c_in, c, radius_spacings * h[lv], num_basis))
            c_in = c
        self.head = GravityHead(grids[levels[-1]], c_in)
        self.votes = EdgeVotes(top, self.head.candidates, 4 * in_channels + channels[0],
                               h[levels[0]]) if edge_votes else None
        self.polish = UpPolish(grids[level], h[level]) if polish else None
        self.level_prior = 0.0
        object.__setattr__(self, "sign_check", None)  # a test-time setting: not in the state
        self.register_buffer("view_pos", grids[level].pos.double(), persistent=False)
        self.register_buffer("view_area", grids[level].area.double(), persistent=False)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> dict:
        """The gravity estimate ``{"up": [B, 3], "logits": [B, Nc], "margin": [B], ...}`` for
        ``x [B, N, in_channels]`` and an optional ``mask [N]`` (polished in evaluation mode).
        """
        x = grayscale(x) if self.gray else x
        m, x_in = mask, x
        if self.pre is not None:
            x, mp = self.pre(x, m)
            m = None if m is None else mp
        image = self.fill(x, m)
        x = self.jet_norm(self.jet(image), mask=m, node_weight=self.area.to(x.dtype))
        votes = None
        for s, stage in enumerate(self.stages):
            if s:
                x, mp = self.pools[s - 1](x, m)
                m = None if m is None else mp
            y = stage(x, m)
            if not s and self.votes is not None:  # edge weights from the first stage's in+out
                votes = self.votes(image, torch.cat([y, x], -1), m)
            x = y
        if self.level_prior and mask is not None:
            level = level_scores(self.head.candidates, self.view_pos, self.view_area, mask,
                                 self.level_prior).to(x.dtype)
            votes = level if votes is None else votes + level
        out = self.head(x, m, votes)
        if self.polish is not None and not self.training:  # training reads the head's scores only
            out["up_head"] = out["up"]
            out["up"] = self.polish(x_in, mask, out["up"])
        if self.sign_check is not None and not self.training:
            out["up"] = self.sign_check(x_in, mask, out["up"])
        return out

    def set_sign_check(self, check) -> None:
        """Passes the estimate through ``check`` (a :class:`~usf_graph.models.SignCheck` for
        this net's input grid) at test time; ``None`` removes it. It stays out of the
        ``state_dict`` and of ``.to()``: move it with the model yourself."""
        if check is not None and len(check.area) != len(self.view_pos):
            raise ValueError(f"the sign check reads {len(check.area)} points, this up estimate's "
                             f"input has {len(self.view_pos)}: build it for the same level and "
                             "refine (SignCheck.refined)")
        object.__setattr__(self, "sign_check", check)


def set_level_prior(model: nn.Module, strength: float) -> int:
    """Sets ``level_prior`` on every :class:`UpNet` in ``model`` (a trained segmenter or
    detector with ``gravity=True``, or an ``UpNet``): for cameras mounted level, without an
    IMU; 0 turns it off. Returns how many it set (0: the model has no up estimate)."""
    strength = float(strength)
    if not math.isfinite(strength) or strength < 0:
        raise ValueError(f"level_prior must be a finite number >= 0 (0: off), got {strength}")
    nets = [m for m in model.modules() if isinstance(m, UpNet)]
    for net in nets:
        net.level_prior = strength
    return len(nets)


def _check_upright(upright: bool, gravity: bool) -> None:
    if upright and not gravity:
        raise ValueError("upright=True reads the up estimate: it needs gravity=True")


class WithUp(GeometryModule):
    r"""The optional up estimate of the dense spherical models (``self.gravity``, an
    :class:`UpNet`).

    With it the network reads, besides the image, each point's height
    :math:`p \cdot u` as one more input channel: ``forward(x, mask, up=None, ...)`` takes u
    from ``up [B, 3]`` when given (a known gravity: an IMU, or the training views' labels),
    else from the :class:`UpNet`'s estimate ``{"up": [B, 3], "logits": [B, Nc]}`` (trained
    by :meth:`GravityHead.loss`). The estimate rotates with the image, so the heights are
    invariant and the outputs stay equivariant.

    ``gray`` (a config entry of every model built on it): the model, up estimate
    included, reads only the luma of its RGB input (:func:`~usf_graph.nn.colour.grayscale`),
    as a mono camera records it; trained so (``usf-graph train seg|det --gray``), it gives
    the same outputs for a colour image and for its gray version."""

    gravity: UpNet | None

    def _gravity_net(self, gravity: bool, in_channels: int, level: int, refine: int = 0,
                     gray: bool = False):
        """Builds ``self.gravity`` for inputs ``[B, N, in_channels]`` on
        ``icosahedral(level + refine)``; ``gray``: the model reads its input's luma only
        (:func:`~usf_graph.nn.colour.grayscale`), the up estimate included."""
        self.gray = check_gray(gray, in_channels)
        self.gravity = UpNet(in_channels, level, refine=refine, gray=gray) if gravity else None
        self._input = (in_channels, level + refine)
        if gravity:
            pos = icosahedral(level + refine).pos
            self.register_buffer("in_pos", pos.double(), persistent=False)

    @property
    def input_grid(self) -> str:
        """The grid its inputs are lifted to, as a spec (``icosahedral:L``)."""
        return f"icosahedral:{self._input[1]}"

    @property
    def trains_up(self) -> bool:
        """Whether the up estimate exists and is trainable (not frozen)."""
        return self.gravity is not None and any(p.requires_grad for p in self.gravity.parameters())

    def _with_height(self, x: torch.Tensor, mask: torch.Tensor | None,
                     up: torch.Tensor | None, estimate: bool = False
                     ) -> tuple[torch.Tensor, dict | None, torch.Tensor | None]:
        """``(x with the height channel when there is a gravity estimate, the estimate, the
        unit up for an upright backbone, else None)``.
        The :class:`UpNet` runs when ``up`` is not given, in training while it is trainable
        (its loss needs the estimate) or when ``estimate`` asks for it; else the estimate
        is ``None``. A gray model reads ``x``'s luma from here on."""
        x = grayscale(x) if self.gray else x
        if self.gravity is None:
            if up is not None:
                raise ValueError("up is only read by models built with gravity=True")
            return x, None, None
        m = check_input(x, mask, len(self.in_pos), *self._input)
        if up is not None and (up.shape != (len(x), 3) or check_values() and (
                not torch.isfinite(up).all() or not bool((up.norm(dim=-1) > 0).all()))):
            raise ValueError(f"up must be finite, nonzero vectors [B, 3] = {(len(x), 3)} (each "
                             f"view's gravity direction), got shape {tuple(up.shape)}")
        trained = self.training and self.trains_up
        grav = self.gravity(x, m) if up is None or trained or estimate else None
        up = grav["up"] if up is None else up.to(x.dtype)
        up = up / up.norm(dim=-1, keepdim=True)
        return (torch.cat([x, heights(self.in_pos, up)], -1), grav,
                up if self.backbone.upright else None)


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


__all__ = ["SphericalBackbone", "SphericalUNet", "UpNet", "WithUp", "ConvStage", "blur", "FillHidden", "level_spacing"]
