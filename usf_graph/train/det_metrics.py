"""COCO AP for spherical boxes: pycocotools' ``COCOeval`` with the exact spherical IoU.

This is how the panorama detection community evaluates (PANDORA, Sph2Pob): the matching,
the 101-point precision curves and the averaging are pycocotools' own; only the IoU of two
boxes is replaced by :func:`usf_graph.ops.pairwise_box_iou` in float64, and every box's
area is set to 1, so only the "all" area range is meaningful.

A camera narrower than the sphere cuts some objects at its border, and their true boxes
reach past what it sees. Those boxes can be *ignored* (``coco_ap(..., ignore=)``), as
KITTI's "don't care" regions and COCO's crowd regions are: a detection on one is neither
a hit nor a false one, and missing it costs nothing. The protocols ignore the true boxes
of which the camera sees less than :data:`FULLY_SEEN` (:func:`~usf_graph.ops.share_in_view`).
"""

from __future__ import annotations

import contextlib
import io

import numpy as np
import torch

from ..ops import box_area, pairwise_box_iou

__all__ = ["FULLY_SEEN", "coco_ap", "usf_map"]

#: A true box counts when the camera sees at least this share of its solid angle; one cut
#: more by the border of the field of view is ignored (``coco_ap(..., ignore=)``).
FULLY_SEEN = 0.9


def _cocoeval():
    from pycocotools.cocoeval import COCOeval

    class SphericalCOCOeval(COCOeval):
        """``COCOeval`` whose ``bbox`` IoU is the exact spherical one; against a crowd
        (ignored) box, as pycocotools does for crowds, the share of the detection inside
        it, so that a detection of the part the camera sees matches it."""

        def computeIoU(self, imgId, catId):  # noqa: N802 - pycocotools' name
            gt, dt = self._gts[imgId, catId], self._dts[imgId, catId]
            if not gt and not dt:
                return []
            order = np.argsort([-d["score"] for d in dt], kind="mergesort")  # as COCOeval does
            dt = [dt[i] for i in order][: self.params.maxDets[-1]]
            if not gt or not dt:
                return np.zeros((len(dt), len(gt)))
            d, g = np.array([d["bbox"] for d in dt]), np.array([g["bbox"] for g in gt])
            iou = pairwise_box_iou(d, g, dtype=torch.float64).numpy()
            crowd = np.array([bool(x["iscrowd"]) for x in gt])
            if crowd.any():  # |D n G| = IoU (|D| + |G|) / (1 + IoU), over |D|
                ad, ag = box_area(d)[:, None], box_area(g[crowd])[None]
                iou[:, crowd] = iou[:, crowd] * (ad + ag) / (1 + iou[:, crowd]) / ad
            return iou

    return SphericalCOCOeval


def _coco(images, anns, cats):
    from pycocotools.coco import COCO

    c = COCO()
    c.dataset = {"images": images, "annotations": anns, "categories": cats}
    with contextlib.redirect_stdout(io.StringIO()):
        c.createIndex()
    return c


def coco_ap(truth, detections, num_classes: int, ignore=None) -> dict:
    """COCO AP, AP50 and AP75 of spherical detections, and AR50: the share of true boxes
    found at IoU 0.5 by the 100 best detections of their image (pycocotools' recall at
    that threshold, averaged over the classes that have true boxes). AR50 against AP50
    splits a detector's losses into objects never found and found objects ranked below
    false ones.

    Args:
        truth: per image, ``(boxes [G, 5], classes [G])`` (radians, any frame).
        detections: per image, ``(boxes [D, 5], classes [D], scores [D])`` in the same frame.
        num_classes: classes are ``0 .. num_classes - 1``.
        ignore: per image, bool ``[G]``: true boxes to ignore (pycocotools' crowds; module
            docstring). ``None``: every box counts.

    Returns ``{"AP": ..., "AP50": ..., "AP75": ..., "AR50": ...}`` in [0, 1] (-1 where no
    class has a ground-truth box, as pycocotools reports it).
    """
    _per_image(truth, detections, "detections")
    images = [{"id": i + 1} for i in range(len(truth))]
    cats = [{"id": k + 1, "name": str(k)} for k in range(num_classes)]
    if ignore is None:
        ignore = [np.zeros(len(np.asarray(gc).reshape(-1)), bool) for _, gc in truth]
    _per_image(truth, ignore, "ignore flags")
    gts, dts = [], []
    for i, ((gb, gc), (db, dc, ds), ig) in enumerate(zip(truth, detections, ignore)):
        (gb, gc, _), ig = _image(i, gb, gc, num_classes, "true"), np.asarray(ig, bool)
        if ig.shape != gc.shape:
            raise ValueError(f"image {i}: {len(gc)} true boxes but {ig.size} ignore flags")
        for b, c, x in zip(gb, gc, ig):
            gts.append({"id": len(gts) + 1, "image_id": i + 1, "category_id": int(c) + 1,
                        "bbox": b.tolist(), "area": 1.0, "iscrowd": int(x)})
        for b, c, s in zip(*_image(i, db, dc, num_classes, "detected", ds)):
            dts.append({"id": len(dts) + 1, "image_id": i + 1, "category_id": int(c) + 1,
                        "bbox": b.tolist(), "score": float(s), "area": 1.0, "iscrowd": 0})
    ev = _cocoeval()(_coco(images, gts, cats), _coco(images, dts, cats), "bbox")
    with contextlib.redirect_stdout(io.StringIO()):
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    rec = ev.eval["recall"][0, :, 0, -1]  # IoU 0.5, every class, all areas, 100 detections
    ar50 = float(rec[rec > -1].mean()) if (rec > -1).any() else -1.0
    return {"AP": float(ev.stats[0]), "AP50": float(ev.stats[1]), "AP75": float(ev.stats[2]),
            "AR50": ar50}


def _per_image(truth, other, what: str) -> None:
    """Refuses ``other`` unless it has one entry per image of ``truth`` (``zip`` would cut
    the longer short)."""
    if len(truth) != len(other):
        raise ValueError(f"{len(truth)} images of ground truth but {len(other)} of {what}")


def _image(i: int, boxes, classes, num_classes: int, what: str, scores=None):
    """One image's ``boxes [K, 5]``, ``classes [K]`` (and ``scores [K]``) as arrays, refused
    unless they match in length, the classes are in ``0 .. num_classes - 1`` and the scores
    are finite: pycocotools would score a NaN as a hit and drop an unknown class."""
    b, c = np.asarray(boxes, np.float64).reshape(-1, 5), np.asarray(classes).reshape(-1)
    s = None if scores is None else np.asarray(scores, np.float64).reshape(-1)
    if len(c) != len(b) or (s is not None and len(s) != len(b)):
        raise ValueError(f"image {i}: {len(b)} {what} boxes but {len(c)} classes"
                         + ("" if s is None else f" and {len(s)} scores"))
    if len(c) and ((c < 0) | (c >= num_classes) | (c != np.round(c))).any():
        raise ValueError(f"image {i}: {what} classes must be whole numbers in 0 .. "
                         f"{num_classes - 1}, got {sorted(set(c.tolist()))}")
    if s is not None and not np.isfinite(s).all():
        raise ValueError(f"image {i}: detection scores contain NaN or infinite values")
    return b, c.astype(np.int64), s


def _voc_ap(tp: np.ndarray, num_truth: int) -> float:
    """Area under the precision envelope with the end points (recall 0 and 1) added."""
    hits = np.cumsum(tp)
    rec = np.r_[0.0, hits / num_truth, 1.0]
    prec = np.r_[0.0, hits / np.arange(1, len(tp) + 1), 0.0]
    prec = np.maximum.accumulate(prec[::-1])[::-1]
    return float(np.sum((rec[1:] - rec[:-1]) * prec[1:]))


def usf_map(truth, detections, num_classes: int, iou_threshold: float = 0.10) -> float:
    """USF's "mAP@10" (``iou_threshold=0.10``): AP at one IoU threshold for every (image,
    class) pair that has ground truth, from greedy matching by falling score and the
    all-point precision envelope with end points added, then the mean over the pairs.

    It is not COCO AP (which pools all images of a class and averages over thresholds)
    and reads higher; it is here to compare with USF's published numbers, so, as USF's,
    it counts every true box (no ``ignore``). Arguments as :func:`coco_ap`."""
    aps = []
    _per_image(truth, detections, "detections")
    for i, ((gb, gc), (db, dc, ds)) in enumerate(zip(truth, detections)):
        gb, gc, _ = _image(i, gb, gc, num_classes, "true")
        db, dc, ds = _image(i, db, dc, num_classes, "detected", ds)
        for k in range(num_classes):
            g = gb[gc == k]
            if not len(g):
                continue
            d = db[dc == k][np.argsort(-ds[dc == k], kind="mergesort")]
            if not len(d):
                aps.append(0.0)
                continue
            iou = pairwise_box_iou(d, g, dtype=torch.float64).numpy()
            free, tp = np.ones(len(g), bool), np.zeros(len(d))
            for i in range(len(d)):
                j = np.argmax(np.where(free, iou[i], -1.0))
                if free[j] and iou[i, j] >= iou_threshold:
                    free[j], tp[i] = False, 1.0
            aps.append(_voc_ap(tp, len(g)))
    return float(np.mean(aps)) if aps else -1.0
