r"""An SO(3)-equivariant CenterNet-style detector of spherical boxes.

An isotropic network (distance-only convolutions) outputs scalar fields, and scalar
fields carry no direction. The box head therefore reads every direction from the
*derivatives* of predicted scalar fields at a heatmap peak p, taken by
:class:`~usf_graph.nn.SurfaceJet` and rebuilt in 3D, never from latitude, longitude or a
fixed north:

* the sub-grid centre is :math:`\exp_p(h^2 \nabla o)` for an offset potential o (which
  learns to look like :math:`-d^2/2h^2` around a centre);
* the box's shape is one symmetric tensor on the tangent plane, the matrix logarithm of
  its size :math:`S = \log f_x\, e e^\top + \log f_y\, n n^\top` (e, n its axes). Its
  trace part is a scalar field s; its traceless part is the traceless Hessian of a field
  r plus learned multiples of the traceless outer products of gradients of fields
  :math:`a_k`: :math:`\mathrm{dev}\,S = h^2\,\mathrm{dev}(\nabla^2 r) + \sum_k w_k h^2
  \mathrm{dev}(\nabla a_k \nabla a_k^\top)`. Its eigenvectors are the box's axes and
  :math:`e^{\lambda}` its fields of view;
* S alone cannot orient a square box (it is then a multiple of the identity), yet a
  square turned by 30 degrees is another region. The rectangle's axes, modulo 90
  degrees, come from a spin-4 quantity: the square (as a complex number) of the
  traceless Hessian of a field q plus learned multiples of the fourth powers of the
  gradients :math:`\nabla a_k`, trained towards :math:`e^{4i\varphi}` for the box's
  axis angle :math:`\varphi`. S then says which of the two axes is the long one, and
  by how much.

All of it is built from rotation-equivariant pieces, so for a rotation that maps the grid
onto itself the boxes found in the rotated input are the rotated boxes, to rounding
(tested in float64); for any other rotation up to discretization (the protocol's rotated
test).
"""

from __future__ import annotations

import torch
from torch import nn

from ..frontend import grid_graph
from ..nn import SurfaceJet, up_frame
from ..ops import box_axes, boxes_from_axes
from .centernet import (
    Detector,
    expmap,
    focal_loss,
    heatmap_targets,
    logmap,
    neighbour_table,
)
from .stages import ConvStage, _oriented
from .unet import FillHidden, SphericalBackbone
from .upnet import WithUp, _check_upright

MAX_FOV = 3.1  # radians; a box must stay inside a hemisphere


def _spin2(h: torch.Tensor) -> torch.Tensor:
    """Hessians ``(h11, h12, h22)`` -> their traceless part ``((h11 - h22) / 2, h12)``."""
    return torch.stack([(h[..., 0] - h[..., 2]) / 2, h[..., 1]], -1)


def _mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """The complex product of ``(re, im)`` pairs."""
    return torch.stack([a[..., 0] * b[..., 0] - a[..., 1] * b[..., 1],
                        a[..., 0] * b[..., 1] + a[..., 1] * b[..., 0]], -1)


def _square(z: torch.Tensor) -> torch.Tensor:
    """``(a, b)`` as the complex number a + ib, squared (its spin doubles)."""
    return _mul(z, z)


class SphericalDetector(Detector, WithUp):
    r"""CenterNet on the icosahedral hierarchy, with an SO(3)-equivariant box head.

    Backbone: a :class:`LocalJet` of the input, then conv stages down from
    ``input_level`` to ``min_level`` (Gaussian pooling between levels, a
    :class:`GradientPairs` layer after the first ``pair_stages`` stages), and back up to
    ``head_level`` with Gaussian upsampling and skip connections (a U-Net). The head is a
    per-point linear map to ``num_classes`` heatmap logits and the scalar fields
    ``(s, o, r, a_1..a_K, w_1..w_K)`` of the module docstring (``K = gradient_fields``).

    With ``gravity=True`` it also reads each point's height along an equivariant up
    estimate, as :class:`~usf_graph.models.upnet.WithUp` describes (``forward(x, mask,
    up=None)``; the estimate, when it runs, is returned as ``"gravity"``): PANDORA boxes are upright in
    the world, and objects stand on the floor. With ``upright=True`` as well, the backbone
    reads :class:`~usf_graph.nn.UpJet` features (of the input and of ``up_fields``
    learned fields) and four more head fields give the traceless shape and the spin-4
    axis field in the frame of up's tangential part t (times :math:`t^2` and
    :math:`t^4` as complex numbers, normalized, fading within 30 degrees of the zenith and
    nadir), added to the jet-based ones: an upright box is then one number. With
    ``upright_convs`` (a level), the stages on that level and coarser, the head's included,
    use :class:`~usf_graph.nn.UprightConv`: oriented kernels in the frame of up (the
    detection protocol uses 4; README). ``gray``: it reads only its input's luma, for mono
    cameras (:class:`~usf_graph.models.upnet.WithUp`).

    ``forward(x, mask)`` returns those fields; :meth:`loss` trains them against boxes and
    :meth:`detect` decodes boxes. ``mask [N]`` (a camera's field of view, one for the
    batch) keeps hidden points out of every convolution, normalization and peak.

    Shapes: ``x [B, N, in_channels]`` on ``icosahedral(input_level)`` ->
    ``{"heat": [B, M, num_classes], "s": [B, M], "offset": [B, M, 3], "dev": [B, M, 2],
    "quad": [B, M, 2], "mask": [M] or None, "seen": [N] or None}`` on
    ``icosahedral(head_level)`` (``mask``: the points the camera sees in part; ``seen``: the
    input's mask; ``offset`` in 3D; ``dev``, the traceless shape, and ``quad``, the spin-4
    axis field, in the head's :func:`~usf_graph.nn.tangent_frame`).
    """

    def __init__(self, num_classes: int = 12, in_channels: int = 3, input_level: int = 5,
                 head_level: int = 4, min_level: int = 2, channels=(32, 64, 128, 128),
                 num_basis: int = 3, radius_spacings: float = 3.0, jet_spacings: float = 3.5,
                 pairs: int = 8, pair_stages: int = 2, gradient_fields: int = 4,
                 gravity: bool = False, upright: bool = False, up_fields: int = 8,
                 upright_convs: int | None = None, gray: bool = False):
        super().__init__()
        if not min_level <= head_level <= input_level:
            raise ValueError(f"need min_level <= head_level <= input_level, got {min_level}, "
                             f"{head_level}, {input_level}")
        self.config = dict(num_classes=num_classes, in_channels=in_channels,
                           input_level=input_level, head_level=head_level, min_level=min_level,
                           channels=list(channels), num_basis=num_basis,
                           radius_spacings=radius_spacings, jet_spacings=jet_spacings,
                           pairs=pairs, pair_stages=pair_stages, gradient_fields=gradient_fields,
                           gravity=gravity, upright=upright, up_fields=up_fields,
                           upright_convs=upright_convs, gray=gray)
        _check_upright(upright, gravity)
        self.num_classes, self.K = num_classes, gradient_fields
        self._gravity_net(gravity, in_channels, input_level, gray=gray)
        self.backbone = SphericalBackbone(in_channels + int(gravity), input_level, head_level, min_level,
                                          channels, num_basis, radius_spacings, jet_spacings,
                                          pairs, pair_stages, upright=upright, up_fields=up_fields,
                                          upright_convs=upright_convs)
        self.num_points = self.backbone.num_points
        c_in = self.backbone.out_channels
        h = self.backbone.grids[head_level]
        self.head_stage = ConvStage(h, c_in, c_in, radius_spacings * h.spacing, num_basis,
                                    upright=_oriented(head_level, upright_convs))
        self.upright = upright  # then 4 more fields: the shape along up (module docstring)
        self.head = nn.Linear(c_in, num_classes + 4 + 3 * gradient_fields + 4 * upright)
        e3, w3 = grid_graph(h, jet_spacings * h.spacing)
        self.surface = SurfaceJet(h.pos, e3, w3, h.spacing)
        self.fill = FillHidden(h.pos)
        self.register_buffer("head_pos", h.pos.double(), persistent=False)
        self.register_buffer("input_pos", self.backbone.grids[input_level].pos, persistent=False)
        self.head_spacing = float(h.spacing)
        n1, _ = grid_graph(h, 1.5 * h.spacing)
        self.register_buffer("ring", neighbour_table(n1, len(h.pos)), persistent=False)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Re-initializes every layer; the heatmap biases start at -4.6 (CenterNet's 0.01 prior)."""
        for m in self.modules():
            if m is not self and hasattr(m, "reset_parameters"):
                m.reset_parameters()
        with torch.no_grad():  # CenterNet's prior: heatmaps start near 0.01
            self.head.bias[: self.num_classes].fill_(-4.6)

    @classmethod
    def from_config(cls, config: dict) -> SphericalDetector:
        return cls(**config)

    # -- network ------------------------------------------------------------------------
    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None,
                up: torch.Tensor | None = None) -> dict:
        """The head's fields (class docstring) for ``x [B, N, in_channels]``, ``mask [N]``
        (optional) and a known ``up [B, 3]`` (optional, else the model's estimate when built
        with ``gravity``, returned under ``"gravity"``).
        """
        x, grav, up = self._with_height(x, mask, up)
        x, m = self.backbone(x, mask, up)
        f = self.head(self.head_stage(x, m, up))
        out = self._fields(f, m, up)  # up: None unless upright
        out["seen"] = mask
        if grav is not None:
            out["gravity"] = grav
        return out

    def _fields(self, f: torch.Tensor, mask, up: torch.Tensor | None = None) -> dict:
        """Per-point logits and box fields from the head's scalar outputs (and, for an
        upright detector, the unit ``up [B, 3]`` it read)."""
        C, K, h = self.num_classes, self.K, self.head_spacing
        # [B, M, 3 + K, 5]: jets of o, r, q, a_k; hidden points take their nearest visible
        # value, so the border of the field of view is not an edge
        jet = self.surface(self.fill(f[..., C + 1:C + 4 + K], mask))
        frame = self.surface.frame.to(f.dtype)  # [M, 2, 3]
        g_o = jet[..., 0, :2]
        offset = h * h * (g_o[..., :1] * frame[:, 0] + g_o[..., 1:2] * frame[:, 1])
        dev = _spin2(jet[..., 1, 2:]) * h * h
        quad = _square(_spin2(jet[..., 2, 2:]) * h * h)
        if K:
            z = jet[..., 3:, :2] * h  # [B, M, K, 2] gradients as complex numbers
            z2 = _square(z)
            w, u = f[..., C + 4 + K:C + 4 + 2 * K, None], f[..., C + 4 + 2 * K:C + 4 + 3 * K, None]
            dev = dev + (w * z2 / 2).sum(-2)
            quad = quad + (u * _square(z2)).sum(-2)
        if up is not None:  # shapes given in the frame of up's tangential part t:
            c, s = up_frame(frame, up)  # t = c e1 + s e2, as a complex number, squared
            t2 = _square(torch.stack([c.T, s.T], -1))  # [B, M, 2], |t|^2 = sin^2(angle to up)
            # unit length, but fading within 30 degrees of the zenith and nadir, where t turns fast
            t2 = t2 / t2.norm(dim=-1, keepdim=True).clamp_min(0.25)
            a = f[..., C + 4 + 3 * K:]
            dev = dev + _mul(a[..., :2], t2)
            quad = quad + _mul(a[..., 2:], _square(t2))
        return {"heat": f[..., :C], "s": f[..., C], "offset": offset, "dev": dev, "quad": quad,
                "mask": mask}

    # -- training -----------------------------------------------------------------------
    def targets(self, boxes: torch.Tensor, classes: torch.Tensor, image: torch.Tensor,
                num_images: int) -> dict:
        """Heatmap targets and the regression samples (:func:`heatmap_targets`): for each,
        its image, point and weight, and the offset, mean log size and traceless shape the
        fields must take there (float64)."""
        P = self.head_pos
        heat, near, (pt, box, w) = heatmap_targets(P, boxes.double(), classes, image, num_images,
                                                   self.num_classes, self.head_spacing)
        c, e, _ = box_axes(boxes.double()[box])
        frame = self.surface.frame[pt]  # [R, 2, 3]
        phi = torch.atan2((e * frame[:, 1]).sum(-1), (e * frame[:, 0]).sum(-1))
        lx, ly = boxes[box, 2].double().log(), boxes[box, 3].double().log()
        return {"heat": heat, "nearest": near, "image": image[box], "point": pt, "box": box, "weight": w,
                "offset": logmap(P[pt], c), "s": (lx + ly) / 2,
                "dev": ((lx - ly) / 2)[:, None] * torch.stack([torch.cos(2 * phi), torch.sin(2 * phi)], -1),
                "quad": torch.stack([torch.cos(4 * phi), torch.sin(4 * phi)], -1)}

    def loss(self, out: dict, boxes: torch.Tensor, classes: torch.Tensor,
             image: torch.Tensor) -> tuple[torch.Tensor, dict]:
        r"""Focal loss on the heatmaps plus weighted smooth-L1 losses on the offset (in
        grid spacings), the mean log size, the traceless shape and the spin-4 axis field at
        the regression samples (norms of differences, so the loss is the same in every
        tangent frame)."""
        B = out["heat"].shape[0]
        t = self.targets(boxes, classes, image, B)
        mask = None if out["mask"] is None else out["mask"].expand(B, -1)
        heat = focal_loss(out["heat"], t["heat"].to(out["heat"].dtype), mask)
        if len(boxes) == 0:
            zero = out["s"].sum() * 0
            return heat + zero, {"heat": heat.item(), "offset": 0.0, "size": 0.0, "shape": 0.0}
        at, dt = (t["image"], t["point"]), out["s"].dtype
        w = (t["weight"] / t["weight"].sum()).to(dt)

        def huber(err, beta):
            return (w * nn.functional.smooth_l1_loss(err, torch.zeros_like(err), beta=beta,
                                                     reduction="none")).sum()

        off = huber((out["offset"][at] - t["offset"].to(dt)).norm(dim=-1) / self.head_spacing, 1.0)
        size = huber(out["s"][at] - t["s"].to(dt), 0.1)
        shape = huber((out["dev"][at] - t["dev"].to(dt)).norm(dim=-1), 0.1)
        shape = shape + huber((out["quad"][at] - t["quad"].to(dt)).norm(dim=-1), 0.1)
        total = heat + off + size + shape
        return total, {"heat": heat.item(), "offset": off.item(), "size": size.item(),
                       "shape": shape.item()}

    # -- inference ----------------------------------------------------------------------
    def boxes_at(self, out: dict, b: int, point: torch.Tensor) -> torch.Tensor:
        """The boxes ``[k, 5]`` that image ``b``'s fields give at head points ``point``:
        the centre from the offset, the rectangle's axes (mod 90 degrees) from the spin-4
        field, the long one and the aspect along it from the spin-2 traceless shape."""
        dt = out["offset"].dtype
        frame, p = self.surface.frame.to(dt)[point], self.head_pos.to(dt)[point]
        c = expmap(p, out["offset"][b, point])
        s, dv, q = out["s"][b, point], out["dev"][b, point], out["quad"][b, point]
        phi = torch.atan2(q[:, 1], q[:, 0]) / 4
        arg = torch.atan2(dv[:, 1], dv[:, 0])
        phi = torch.where(torch.cos(2 * phi - arg) < 0, phi + torch.pi / 2, phi)
        r = dv.norm(dim=-1) * torch.cos(2 * phi - arg)
        e = torch.cos(phi)[:, None] * frame[:, 0] + torch.sin(phi)[:, None] * frame[:, 1]
        return boxes_from_axes(c, e, (s + r).exp().clamp(max=MAX_FOV), (s - r).exp().clamp(max=MAX_FOV))


__all__ = ["SphericalDetector"]
