r"""A learned check of an up estimate's sign: is ``u`` up, or is the image upside down?

An up estimate from vanishing directions finds gravity's axis more reliably than its sign
(``docs/seg_det_log.md``, sessions 26-27). :class:`SignCheck` asks a second question of
the image: an upright :class:`~usf_graph.models.SphericalUNet` with one output channel
reads the image with each point's height along a candidate ``u`` and the image's
derivatives along and across it, and scores how upright the view looks,

.. math::
    s(u) = \frac{\sum_i a_i m_i f_i(x, u)}{\sum_i a_i m_i},

the area-weighted (:math:`a_i`) mean of its output over the visible points (:math:`m_i`).
The check turns ``u`` into ``-u`` where :math:`s(-u) > s(u)`. Everything reads ``u`` only
through heights and derivatives along it, so the check rotates with the input.

It is asked only where the camera sees at least ``min_field`` of the sphere: on a
90-degree pinhole (a sixth of it) it flipped more right estimates than wrong ones. The
field's share of the sphere does not change under rotation, so neither does the gate.
Trained by :func:`usf_graph.train.sign.pretrain_sign`; attached to a model's up estimate
by :func:`set_sign_check`.
"""

from __future__ import annotations

import torch
from torch import nn

from ..tracing import field_of
from .stages import refined_copy
from .unet import SphericalUNet
from .upnet import UpNet

#: The share of the sphere a camera must see for the check to be asked (a 190-degree
#: fisheye sees 0.54 of it, a 90-degree pinhole 0.17).
MIN_FIELD = 0.4


class SignCheck(nn.Module):
    r"""Scores and corrects the sign of an up estimate (module docstring).

    Args:
        level: the input's icosahedral level (the model whose estimate it checks).
        in_channels: input channels (3: RGB).
        channels: the U-Net's channels per level, finest first.
        min_field: the least share of the sphere the camera must see for :meth:`forward`
            to flip anything (:data:`MIN_FIELD`).
        refine: inputs on ``icosahedral(level + refine)`` (see :meth:`refined`).

    Shapes: ``score(x [B, N, in_channels], mask [N] or None, up [B, 3]) -> [B]``;
    ``forward(x, mask, up) -> up [B, 3]``, each row ``up`` or ``-up`` (:meth:`correct`
    where the field of view is wide enough, else ``up``).
    """

    def __init__(self, level: int = 5, in_channels: int = 3, channels=(32, 64, 128, 128),
                 min_field: float = MIN_FIELD, refine: int = 0):
        super().__init__()
        if not 0.0 <= min_field <= 1.0:
            raise ValueError(f"min_field is a share of the sphere in [0, 1], got {min_field}")
        self.config = dict(level=level, in_channels=in_channels, channels=list(channels),
                           min_field=min_field, refine=refine)
        # the U-Net's own estimate is never asked (the check is handed its candidate), but
        # gravity=True gives it the height channel and the upright derivatives
        self.net = SphericalUNet(num_classes=1, in_channels=in_channels, level=level,
                                 channels=channels, gravity=True, upright=True, pairs=0,
                                 up_fields=4, refine=refine)
        self.net.gravity.requires_grad_(False)
        self._areas = self.area.detach().cpu().numpy().copy()  # for the gate (asked)

    @property
    def area(self) -> torch.Tensor:
        """The input grid's point areas ``[N]`` (float64), as its up estimate holds them."""
        return self.net.gravity.view_area

    @classmethod
    def from_config(cls, config: dict) -> SignCheck:
        return cls(**config)

    def reset_parameters(self) -> None:
        """Re-initializes the network."""
        self.net.reset_parameters()

    def score(self, x: torch.Tensor, mask: torch.Tensor | None, up: torch.Tensor) -> torch.Tensor:
        """s(up) ``[B]``: the network's area-weighted mean output over the visible points."""
        out = self.net(x, mask, up=up)[..., 0]
        w = self.area.to(out.dtype) * (1 if mask is None else mask.to(out.dtype))
        return (out * w).sum(-1) / w.sum()

    def asked(self, mask: torch.Tensor | None) -> bool:
        """Whether the camera's field of view (``mask [N]``) is wide enough to ask the check."""
        if mask is None:
            return True
        # numpy, as the field of view is (recorded while exporting: the gate is geometry)
        area = self._areas
        return bool((area * field_of(mask)).sum() >= self.config["min_field"] * area.sum())

    def correct(self, x: torch.Tensor, mask: torch.Tensor | None, up: torch.Tensor) -> torch.Tensor:
        """``up [B, 3]`` with the rows where s(-up) > s(up) turned, whatever the field of view."""
        flip = self.score(x, mask, -up) > self.score(x, mask, up)
        return torch.where(flip[:, None], -up, up)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None, up: torch.Tensor) -> torch.Tensor:
        """``up`` with each row's sign corrected where the field of view is wide enough, else ``up``
        as given.
        """
        return self.correct(x, mask, up) if self.asked(mask) else up

    def refined(self, levels: int = 1) -> SignCheck:
        """The same check for inputs ``levels`` grid levels finer, with these weights."""
        return refined_copy(self, levels)

    def __repr__(self) -> str:
        c = self.config
        return (f"{type(self).__name__}(level={c['level']}, channels={c['channels']}, "
                f"min_field={c['min_field']}, refine={c['refine']})")


def set_sign_check(model: nn.Module, check: SignCheck | None) -> int:
    """Makes every :class:`UpNet` in ``model`` (a trained segmenter or detector with
    ``gravity=True``, or an ``UpNet``) pass its estimate through ``check`` at test time
    (``None``: no check). The check is a test-time setting, like ``level_prior``: it is not
    part of the model's ``state_dict`` (save it on its own). Returns how many it set."""
    if check is not None and not isinstance(check, SignCheck):
        raise TypeError(f"check must be a SignCheck or None, got {type(check).__name__}")
    nets = [m for m in model.modules() if isinstance(m, UpNet)]
    for net in nets:
        net.set_sign_check(check)
    return len(nets)


__all__ = ["SignCheck", "set_sign_check", "MIN_FIELD"]
