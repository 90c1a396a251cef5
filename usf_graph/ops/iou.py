r"""Area, exact intersection over union and non-maximum suppression of spherical boxes.

The intersection of two boxes is a convex spherical polygon: box A's corners clipped by the
four great-circle half-spaces of box B (Sutherland-Hodgman on the sphere, where the edge
``p -> q`` meets the plane of normal ``m`` at ``+-((p.m) q - (q.m) p)``). Its area is the sum of
the spherical excesses of a fan of triangles (Girard's theorem), each computed with Van
Oosterom and Strackee's formula :math:`\tan(\Omega/2) = \det[a, b, c] / (1 + a\cdot b +
b\cdot c + c\cdot a)`, which stays accurate for thin and tiny triangles. Points within a
few ulps of a plane count as on it, so identical boxes give 1 and touching boxes 0.

Everything is batched torch, differentiable, and runs on any device. In float64 it is the
exact reference (errors about 1e-12); in float32 it is the fast path for training and NMS
(errors documented in ``benchmarks/README.md``). Fields of view must be below 180 degrees.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..geometry import from_latlon, geodesic_distance
from ..tracing import check_values
from .boxes import _as_boxes, box_planes

__all__ = ["box_area", "box_iou", "nms_keep", "pairwise_box_iou", "spherical_nms"]


def _tensor(boxes, dtype=None) -> torch.Tensor:
    b = _as_boxes(boxes)
    b = b if torch.is_tensor(b) else torch.from_numpy(b)
    return b.to(dtype) if dtype is not None else b


def box_area(boxes):
    """Solid angle (sr) of boxes ``[..., 5]``: :math:`4 \\arcsin(\\sin(f_x/2)\\sin(f_y/2))`
    (equal to PANDORA's inverse-cosine form, written without it; see the tests)."""
    # the formula is symmetric about 180 degrees: a wider box would get a narrower one's area
    return _area(_fields_of_view(_as_boxes(boxes), "area", closed=True))


def _area(b):
    """:func:`box_area` of boxes whose fields of view are already checked."""
    xp = torch if torch.is_tensor(b) else np
    s = xp.sin(b[..., 2] / 2) * xp.sin(b[..., 3] / 2)
    return 4 * (xp.asin(s) if xp is torch else np.arcsin(s))


def _fields_of_view(b, what: str, closed: bool):
    """``b`` as it is, refused unless its fields of view are in [0, 180] degrees
    (``closed``) or [0, 180): a box's edges are great circles, so it spans at most a
    hemisphere, and the IoU's clipping needs less."""
    fov = b[..., 2:4]
    if check_values() and (bool((fov < 0).any()) or bool((fov > math.pi if closed else fov >= math.pi).any())):
        raise ValueError(f"box {what} needs fields of view in [0, 180{']' if closed else ')'} "
                         "degrees (a box's edges are great circles, so it spans at most a "
                         f"hemisphere), got fields of view from {float(fov.min()):.4g} to "
                         f"{float(fov.max()):.4g} rad")
    return b


def _safe_unit(v: torch.Tensor) -> torch.Tensor:
    tiny = torch.finfo(v.dtype).tiny ** 0.5
    return v / (v * v).sum(-1, keepdim=True).clamp_min(tiny).sqrt()


def _clip(poly: torch.Tensor, count: torch.Tensor, m: torch.Tensor, eps: float):
    """Clip convex polygons ``poly [P, S, 3]`` (first ``count`` vertices valid) by the
    half-spaces ``p . m >= 0``, ``m [P, 3]``."""
    P, S, _ = poly.shape
    slot = torch.arange(S, device=poly.device)
    valid = slot < count[:, None]
    nxt_idx = torch.where(slot + 1 < count[:, None], slot + 1, torch.zeros_like(slot))
    nxt = poly.gather(1, nxt_idx[..., None].expand(P, S, 3))
    d = (poly * m[:, None]).sum(-1)
    dn = d.gather(1, nxt_idx)
    keep = valid & (d >= -eps)
    cross = valid & (((d > eps) & (dn < -eps)) | ((d < -eps) & (dn > eps)))
    # (p.m) q - (q.m) p lies on the plane; the sign keeps it between p and q, not opposite
    hit = _safe_unit((d[..., None] * nxt - dn[..., None] * poly) * torch.sign(d - dn)[..., None])
    cand = torch.stack([poly, hit], 2).reshape(P, 2 * S, 3)
    flag = torch.stack([keep, cross], 2).reshape(P, 2 * S)
    # the kept candidates, in order, into the first slots: slot s takes the (s+1)-th
    # flagged one (a gather, which exporters take; a stable sort they may not)
    place = flag.cumsum(1) - 1
    pick = (flag[:, None] & (place[:, None] == slot[None, :, None])).to(torch.uint8).argmax(-1)
    new = cand.gather(1, pick[..., None].expand(P, S, 3))
    return new, flag.sum(1).clamp_max(S)


def _polygon_area(poly: torch.Tensor, count: torch.Tensor) -> torch.Tensor:
    a = poly[:, :1]
    b, c = poly[:, 1:-1], poly[:, 2:]
    det = (a * torch.linalg.cross(b, c, dim=-1)).sum(-1)
    den = 1 + (a * b).sum(-1) + (b * c).sum(-1) + (c * a).sum(-1)
    tri = 2 * torch.atan2(det, den)
    use = torch.arange(2, poly.shape[1], device=poly.device) < count[:, None]
    return torch.where(use, tri, torch.zeros_like(tri)).sum(1).abs()


def box_iou(a, b, dtype=None) -> torch.Tensor:
    """IoU of boxes ``a [..., 5]`` and ``b [..., 5]`` pair by pair (broadcast), as a tensor.

    ``dtype=torch.float64`` gives the exact reference; float32 the fast path.
    """
    a = _fields_of_view(_tensor(a, dtype), "IoU", closed=False)
    b = _fields_of_view(_tensor(b, dtype), "IoU", closed=False)
    a, b = torch.broadcast_tensors(a, b)
    shape = a.shape[:-1]
    a, b = a.reshape(-1, 5), b.reshape(-1, 5)
    eps = 64 * torch.finfo(a.dtype).eps
    _, corners = box_planes(a)
    planes, _ = box_planes(b)
    S = 8  # a quadrilateral clipped by four half-spaces has at most 8 vertices
    poly = torch.cat([corners, corners.new_zeros(len(a), S - 4, 3)], 1)
    count = torch.full((len(a),), 4, device=a.device)
    for k in range(4):
        poly, count = _clip(poly, count, planes[:, k], eps)
    inter = _polygon_area(poly, count)
    union = _area(a) + _area(b) - inter
    iou = inter / union.clamp_min(torch.finfo(a.dtype).tiny)
    return iou.clamp(0, 1).reshape(shape)


def pairwise_box_iou(a, b, dtype=None, chunk: int = 65536) -> torch.Tensor:
    """IoU matrix ``[N, M]`` of boxes ``a [N, 5]`` and ``b [M, 5]``, in chunks of pairs.
    Pairs whose circumscribed caps are apart (:func:`_caps_meet`) are 0 without clipping,
    where values can be read; an exported program computes every pair."""
    a, b = _tensor(a, dtype).reshape(-1, 5), _tensor(b, dtype).reshape(-1, 5)
    if not check_values():  # fixed shapes: every pair, as the exporters trace it
        rows = max(1, chunk // max(len(b), 1))
        out = [box_iou(a[i:i + rows, None], b[None]) for i in range(0, len(a), rows)]
        return torch.cat(out) if out else a.new_zeros(0, len(b))
    dt = torch.promote_types(a.dtype, b.dtype)
    a = _fields_of_view(a.to(dt), "IoU", closed=False)
    b = _fields_of_view(b.to(dt), "IoU", closed=False)
    i, j = _caps_meet(a, b).nonzero(as_tuple=True)
    vals = [box_iou(a[i[k:k + chunk]], b[j[k:k + chunk]]) for k in range(0, len(i), chunk)]
    vals = torch.cat(vals) if vals else a.new_zeros(0)
    return a.new_zeros(len(a), len(b)).index_put((i, j), vals)


def _caps_meet(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    r"""``[N, M]`` bool: False where box ``a[n]``'s and box ``b[m]``'s circumscribed caps are
    apart, so that the boxes share no point (their IoU is 0). A box lies in the cap about
    its centre through its corners, at :math:`\arctan\sqrt{\tan^2(f_x/2) +
    \tan^2(f_y/2)}` (below 90 degrees, where a cap is convex). Computed in float64, with
    a margin far above its rounding: a pair it keeps is clipped as before."""
    a, b = a.detach().double(), b.detach().double()

    def cap(x):
        sx, cx = torch.sin(x[:, 2] / 2), torch.cos(x[:, 2] / 2)
        sy, cy = torch.sin(x[:, 3] / 2), torch.cos(x[:, 3] / 2)
        radius = torch.atan2(torch.sqrt((sx * cy) ** 2 + (cx * sy) ** 2), cx * cy)
        return from_latlon(x[:, 1], x[:, 0]), radius

    (ca, ra), (cb, rb) = cap(a), cap(b)
    return geodesic_distance(ca[:, None], cb[None]) <= ra[:, None] + rb[None] + 1e-9


def spherical_nms(boxes, scores, iou_threshold: float, classes=None) -> torch.Tensor:
    """Indices of the boxes kept by greedy non-maximum suppression with the spherical IoU,
    highest score first (as ``torchvision.ops.nms``); with ``classes [N]``, boxes suppress
    only boxes of their own class (as ``torchvision.ops.batched_nms``)."""
    boxes, scores = _tensor(boxes).reshape(-1, 5), torch.as_tensor(scores)
    if scores.shape != (len(boxes),):
        raise ValueError(f"scores must have shape [{len(boxes)}] (one per box), got {tuple(scores.shape)}")
    if not bool(torch.isfinite(scores).all()):
        raise ValueError("scores contain NaN or infinite values")
    order = torch.argsort(scores, descending=True)
    cls = None if classes is None else torch.as_tensor(classes).reshape(-1)[order]
    return order[nms_keep(boxes[order], torch.ones(len(order), dtype=torch.bool), iou_threshold, cls)]


def nms_keep(boxes: torch.Tensor, alive: torch.Tensor, iou_threshold: float,
             classes: torch.Tensor | None = None) -> torch.Tensor:
    """Greedy NMS on boxes ``[N, 5]`` already in order of falling score: bool ``[N]``, the
    boxes of ``alive [N]`` (bool) that no better kept box (of their class, with
    ``classes [N]``) overlaps by more than ``iou_threshold``; boxes not alive suppress
    nothing. A fixed sequence of N steps and no branch on values, so an exported detector
    traces it (:class:`~usf_graph.train.bound.BoundDetector`)."""
    if check_values():  # only the live boxes, a few of the top k, take part
        live = alive.nonzero().squeeze(1)
        kept = _greedy(boxes[live], alive[live], iou_threshold,
                       None if classes is None else classes[live])
        return torch.zeros_like(alive).index_put((live,), kept)
    return _greedy(boxes, alive, iou_threshold, classes)


def _greedy(boxes, alive, iou_threshold, classes):
    """:func:`nms_keep` over every row: a fixed sequence of ``len(boxes)`` steps."""
    over = pairwise_box_iou(boxes, boxes) > iou_threshold
    if classes is not None:
        over = over & (classes[:, None] == classes[None, :])
    over = torch.triu(over, diagonal=1)  # a box suppresses only worse ones
    for i in range(len(boxes)):
        alive = alive & ~(alive[i] & over[i])
    return alive
