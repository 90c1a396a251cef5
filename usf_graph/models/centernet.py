r"""CenterNet pieces shared by the spherical detector and its planar baseline.

A detector of this kind predicts, per class, a heatmap over a set of output points (grid
points on S2, or pixel centres of a planar feature map) that peaks at box centres, and,
at each peak, the box's shape. Both detectors here place the heatmap targets by
geodesic distance on the sphere, so they learn the same targets from the same boxes.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from ..geometry import from_latlon, geodesic_distance, tangent_towards
from ..nn.precision import GeometryModule
from ..ops import spherical_nms

# A box's heatmap is a Gaussian of geodesic distance with this share of its size as sigma,
# never narrower than half an output spacing (CenterNet ties it to the box size likewise).
SIGMA_SHARE = 0.1


def box_centres(boxes: torch.Tensor) -> torch.Tensor:
    """Centre directions ``[K, 3]`` of boxes ``[K, 5]``."""
    return from_latlon(boxes[:, 1], boxes[:, 0])


def nearest_points(boxes: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Index ``[K]`` of the point of ``points [M, 3]`` (unit) nearest each box's centre
    (``boxes [K, 5]``; the centres in float64, so float32 boxes pick the same points)."""
    return (box_centres(boxes.double()).to(points.dtype) @ points.T).argmax(1)


def centres_seen(boxes: np.ndarray, points: torch.Tensor, seen: torch.Tensor | None, b: int = 0):
    """Bool ``[D]``: whether the camera sees the input point (of ``points [N, 3]``, unit)
    nearest the centre of each box (``boxes [D, 5]``) of image ``b``; ``seen [N]`` (or
    ``[B, N]``, per image) is its field of view (``None``: everything, and ``None`` is
    returned)."""
    if seen is None:
        return None
    seen = seen.cpu() if seen.dim() == 1 else seen[b].cpu()
    return seen[nearest_points(torch.as_tensor(boxes).reshape(-1, 5), points.detach().cpu())]


def logmap(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Tangent vectors at unit ``p`` pointing to ``q`` with length their geodesic distance."""
    return tangent_towards(p, q) * geodesic_distance(p, q)[..., None]


def expmap(p: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """The unit vector reached from ``p`` along tangent ``v`` for the length ``|v|``."""
    n = v.norm(dim=-1, keepdim=True)
    return torch.cos(n) * p + torch.sin(n) * v / n.clamp_min(1e-300)


def heatmap_targets(points: torch.Tensor, boxes: torch.Tensor, classes: torch.Tensor,
                    image: torch.Tensor, num_images: int, num_classes: int,
                    spacing: float, min_weight: float = 0.05):
    r"""CenterNet heatmap targets on output points, and where each box's shape is learnt.

    For class k at point q: :math:`\max_b e^{-d(q, c_b)^2 / 2\sigma_b^2}` over the boxes
    of class k in the image, :math:`\sigma_b = \max(0.1 \sqrt{f_x f_y}, h / 2)`; the point
    nearest each centre is set to exactly 1 (the positives of :func:`focal_loss`).
    Every point where some box's Gaussian reaches ``min_weight`` regresses the box whose
    Gaussian is highest there, weighted by it (TTFNet's dense regression: many more
    samples than the centre point alone, so the box head learns in few epochs).

    Args:
        points: ``[M, 3]`` unit vectors of the output points (the same for every image).
        boxes: ``[K, 5]`` all boxes of the batch; classes ``[K]``; image ``[K]`` the image
            each belongs to; spacing: h, the output points' spacing (radians).

    Returns ``(target [num_images, M, num_classes], nearest [K], (point [R], box [R],
    weight [R]))``: the heatmaps, each box's centre point, and the regression samples
    (point index, index of its box, weight).
    """
    K = len(boxes)
    if boxes.shape != (K, 5) or classes.shape != (K,) or image.shape != (K,):
        raise ValueError(f"need boxes [K, 5], classes [K] and image [K], got {tuple(boxes.shape)}, "
                         f"{tuple(classes.shape)} and {tuple(image.shape)}")
    if K and not (0 <= int(classes.min()) and int(classes.max()) < num_classes):
        raise ValueError(f"box classes must be in [0, {num_classes}), got {int(classes.min())} to "
                         f"{int(classes.max())}: is the dataset's label space the model's?")
    if K and not (0 <= int(image.min()) and int(image.max()) < num_images):
        raise ValueError(f"box image indices must be in [0, {num_images}) (the batch), got "
                         f"{int(image.min())} to {int(image.max())}")
    M = len(points)
    target = points.new_zeros(num_images * num_classes, M)
    if len(boxes) == 0:
        none = classes.new_zeros(0)
        return (target.view(num_images, num_classes, M).transpose(1, 2), none,
                (none, none, points.new_zeros(0)))
    c = box_centres(boxes).to(points.dtype)
    nearest = nearest_points(boxes, points)
    d = geodesic_distance(c[:, None], points[None])  # [K, M]
    sigma = torch.clamp(SIGMA_SHARE * (boxes[:, 2] * boxes[:, 3]).sqrt().to(points.dtype), min=spacing / 2)
    g = torch.exp(-0.5 * (d / sigma[:, None]) ** 2)
    g[torch.arange(len(c), device=g.device), nearest] = 1.0
    target.scatter_reduce_(0, (image * num_classes + classes)[:, None].expand(-1, M), g, "amax")
    # per image and point, the box with the highest Gaussian
    best = points.new_zeros(num_images, M).scatter_reduce(0, image[:, None].expand(-1, M), g, "amax")
    own = (g >= best[image]) & (g >= min_weight)
    box, point = torch.nonzero(own, as_tuple=True)
    return target.view(num_images, num_classes, M).transpose(1, 2), nearest, (point, box, g[box, point])


def focal_loss(logits: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None,
               alpha: float = 2.0, beta: float = 4.0) -> torch.Tensor:
    r"""CenterNet's penalty-reduced focal loss, summed and divided by the number of
    positives (``target == 1``); ``mask [B, M]`` leaves hidden points out.

    .. math::
        -\frac{1}{N_+}\sum \begin{cases} (1-p)^\alpha \log p & y = 1\\
        (1-y)^\beta p^\alpha \log(1-p) & \text{otherwise} \end{cases}
    """
    logp, log1mp = F.logsigmoid(logits), F.logsigmoid(-logits)
    p = torch.sigmoid(logits)
    pos = target >= 1.0
    loss = torch.where(pos, (1 - p) ** alpha * logp, (1 - target) ** beta * p ** alpha * log1mp)
    if mask is not None:
        loss = loss * mask[..., None].to(loss.dtype)
    return -loss.sum() / pos.sum().clamp_min(1)


def peaks(prob: torch.Tensor, neighbours: torch.Tensor, k: int, threshold: float):
    """The ``k`` highest local maxima of ``prob [M, C]`` above ``threshold``: a point is a
    maximum of class c when no neighbour (``neighbours [2, E]``, row 0 the neighbour, row 1
    the centre) is higher. Returns ``(point [D], class [D], score [D])`` by falling score."""
    j, i = neighbours
    M, C = prob.shape
    top = prob.new_full((M, C), -math.inf).scatter_reduce(0, i[:, None].expand(-1, C), prob[j], "amax")
    keep = (prob >= top) & (prob > threshold)
    score = torch.where(keep, prob, torch.zeros_like(prob)).flatten()
    s, idx = score.topk(min(k, score.numel()))
    ok = s > threshold
    return idx[ok] // C, idx[ok] % C, s[ok]


def fields_on_cpu(out: dict) -> dict:
    """A detector's output fields, detached and on the CPU, where boxes are decoded (peaks,
    NMS and cameras work per image, in numpy)."""
    return {k: v.detach().cpu() if torch.is_tensor(v) else v for k, v in out.items()}


def detections(boxes: np.ndarray, cls: torch.Tensor, score: torch.Tensor,
               nms: float | None, seen: torch.Tensor | None = None) -> dict:
    """One image's decoded peaks as ``{"boxes", "classes", "scores"}`` (numpy), after
    class-wise spherical NMS at IoU ``nms`` (``None``: none), best first. ``seen [D]``
    (bool): the peaks kept before NMS (``None``: all), so that a dropped one suppresses
    nothing."""
    if seen is not None:
        seen = seen.cpu()
        boxes, cls, score = boxes[seen.numpy()], cls[seen], score[seen]
    keep = torch.arange(len(boxes))
    if nms is not None and len(boxes):
        kept = [torch.nonzero(cls == k).flatten() for k in cls.unique().tolist()]
        keep = torch.cat([i[spherical_nms(torch.as_tensor(boxes[i.numpy()]), score[i], nms)]
                          for i in kept])
        keep = keep[score[keep].argsort(descending=True)]
    keep = keep.numpy()
    return {"boxes": boxes[keep], "classes": cls[keep].numpy(), "scores": score[keep].numpy()}


class Detector(GeometryModule):
    """What both detectors share: ``detect(x, mask, **decode_kw)`` in evaluation mode."""

    input_dims = 3  # x without its batch dimension

    @torch.no_grad()
    def detect(self, x: torch.Tensor, mask: torch.Tensor | None = None, **kw) -> list[dict]:
        """``decode(forward(x, mask), **kw)`` in evaluation mode, for a batch or one sample."""
        was = self.training
        self.eval()
        try:
            return self.decode(self(x if x.dim() == self.input_dims else x[None], mask), **kw)
        finally:
            self.train(was)

    def _centres_seen(self, out: dict, boxes: np.ndarray, b: int, drop_hidden: bool):
        """:func:`centres_seen` of image ``b``'s boxes on the input's points
        (``self.input_pos``), or ``None`` (keep all) without ``drop_hidden`` or a mask."""
        return centres_seen(boxes, self.input_pos, out.get("seen") if drop_hidden else None, b)
