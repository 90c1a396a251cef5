r"""CenterNet pieces shared by the spherical detector and its planar baseline.

A detector of this kind predicts, per class, a heatmap over a set of output points (grid
points on S2, or pixel centres of a planar feature map) that peaks at box centres, and,
at each peak, the box's shape. Both detectors here place the heatmap targets by
geodesic distance on the sphere, so they learn the same targets from the same boxes.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..geometry import from_latlon, geodesic_distance, tangent_towards
from ..nn.precision import GeometryModule
from ..ops import nms_keep
from ..sparse import padded_rows, row_pointers

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


def logmap(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Tangent vectors at unit ``p`` pointing to ``q`` with length their geodesic distance."""
    return tangent_towards(p, q) * geodesic_distance(p, q)[..., None]


def expmap(p: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """The unit vector reached from ``p`` along tangent ``v`` for the length ``|v|``."""
    n = v.norm(dim=-1, keepdim=True)
    return torch.cos(n) * p + torch.sin(n) * v / n.clamp_min(torch.finfo(v.dtype).tiny)


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


def neighbour_table(edges: torch.Tensor, num_points: int) -> torch.Tensor:
    """Each point and its neighbours (``edges [2, E]``, row 0 the neighbour, row 1 the
    centre) as a table ``[M, R]`` (int64), each row starting with its own point and padded
    with it: what :func:`peaks` gathers from."""
    j, i = edges.long()
    own = torch.arange(num_points, device=edges.device)
    order = torch.argsort(i, stable=True)
    cols, slot = padded_rows(row_pointers(torch.bincount(i, minlength=num_points)), j[order])
    table = torch.where(slot[:, 0] == len(j), own[:, None], cols.long())
    return torch.cat([own[:, None], table], 1)


def peaks(prob: torch.Tensor, table: torch.Tensor, k: int, threshold: float):
    """The ``k`` highest local maxima of ``prob [M, C]``: a point is a maximum of class c
    when no point of its row of ``table [M, R]`` (:func:`neighbour_table`) is higher.
    Returns ``(point [k], class [k], score [k])`` by falling score, fixed in shape (an
    exported detector traces it): the peaks are the rows whose score is above
    ``threshold``; the rest score 0."""
    C = prob.shape[1]
    keep = (prob >= prob[table].amax(1)) & (prob > threshold)
    score = torch.where(keep, prob, torch.zeros_like(prob)).flatten()
    s, idx = score.topk(min(k, score.numel()))
    return idx // C, idx % C, s


def fields_on_cpu(out: dict) -> dict:
    """A detector's output fields, detached, on the CPU and floating ones in float64, where
    eager decoding runs (peaks, boxes and NMS in double precision)."""
    return {k: (v.detach().cpu().double() if v.is_floating_point() else v.detach().cpu())
            if torch.is_tensor(v) else v for k, v in out.items()}


class Detector(GeometryModule):
    """What both detectors share: decoding (:meth:`decode`, :meth:`decode_image`) from a
    subclass's :meth:`boxes_at`, and ``detect(x, mask, **decode_kw)`` in evaluation mode."""

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

    def decode(self, out: dict, k: int = 100, threshold: float = 0.05,
               nms: float | None = 0.5, drop_hidden: bool = True) -> list[dict]:
        """Boxes from the fields of ``forward``, per image: ``{"boxes": [D, 5] (float64
        numpy, radians), "classes": [D], "scores": [D]}``, best first, decoded in float64 on
        the CPU (:meth:`decode_image`)."""
        out, res = fields_on_cpu(out), []
        for b in range(out["heat"].shape[0]):
            boxes, cls, score, kept = self.decode_image(out, b, k, threshold, nms, drop_hidden)
            res.append({"boxes": boxes[kept].numpy().reshape(-1, 5), "classes": cls[kept].numpy(),
                        "scores": score[kept].numpy()})
        return res

    def decode_image(self, out: dict, b: int, k: int = 100, threshold: float = 0.05,
                     nms: float | None = 0.5, drop_hidden: bool = True):
        """Image ``b``'s detections in fixed shapes, in the fields' dtype and on their
        device (what an exported detector traces): ``(boxes [k, 5], classes [k], scores
        [k], kept [k] bool)``, best first; the detections are the kept rows. Peaks
        (:func:`peaks` over the output points' one-ring, inside the mask) above
        ``threshold``; with ``drop_hidden``, less those whose box centre falls on an input
        point the camera does not see (``out["seen"]``: a point the camera sees in part can
        put a centre outside the view, where it can only be a guess; ``False`` keeps boxes
        of objects the view cuts); then greedy NMS per class at IoU ``nms`` (``None``:
        none), in which dropped peaks suppress nothing."""
        prob = torch.sigmoid(out["heat"][b])
        if out["mask"] is not None:
            prob = prob * out["mask"][:, None].to(prob.dtype)
        pt, cls, score = peaks(prob, self.ring.to(prob.device), k, threshold)
        boxes = self.boxes_at(out, b, pt)
        kept = score > threshold
        seen = out.get("seen") if drop_hidden else None
        if seen is not None:
            seen = seen if seen.dim() == 1 else seen[b]
            kept = kept & seen.to(kept.device)[nearest_points(boxes, self.input_pos.to(boxes.device))]
        if nms is not None:
            kept = nms_keep(boxes, kept, nms, cls)
        return boxes, cls, score, kept

    def boxes_at(self, out: dict, b: int, point: torch.Tensor) -> torch.Tensor:
        """The boxes ``[k, 5]`` (radians) that image ``b``'s fields give at output points
        ``point [k]``."""
        raise NotImplementedError
