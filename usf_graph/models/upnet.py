r"""The up estimate of the dense spherical models: :class:`UpNet`, which estimates the
direction of up from the image, equivariantly, and :class:`WithUp`, through which a
segmenter or detector reads it (or a known gravity) as each point's height.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from ..frontend import grid_graph
from ..grids import icosahedral
from ..nn import (
    FillHidden,
    LocalJet,
    MaskedBatchNorm,
)
from ..nn.colour import check_gray, grayscale
from ..nn.precision import GeometryModule
from ..tracing import check_values
from .gravity import EdgeVotes, GravityHead, UpPolish, heights, level_scores
from .stages import ConvStage, blur, check_input, level_spacing


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
