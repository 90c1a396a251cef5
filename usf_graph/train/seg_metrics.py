r"""Segmentation metrics from a confusion matrix, a test set's scores, and the loss's
class weights.

The standard protocol (and ours) accumulates one confusion matrix over the whole test set
and reads per-class IoU and accuracy from it:

.. math::
    \mathrm{IoU}_c = \frac{M_{cc}}{\sum_k M_{ck} + \sum_k M_{kc} - M_{cc}}, \qquad
    \mathrm{Acc}_c = \frac{M_{cc}}{\sum_k M_{ck}}

(rows: truth, columns: prediction). mIoU averages the classes that occur in the truth or
the predictions, mAcc the classes that occur in the truth. On the sphere, each point
counts with its area (``weight``), which makes the numbers independent of the grid's
density. USF's reference code instead averages a per-image mIoU
(:func:`per_image_miou`); it is offered for comparison with its table only.
"""

from __future__ import annotations

import numpy as np
import torch

from ..scenes import SEMANTIC_CLASSES


def confusion_matrix(pred, target, num_classes: int, ignore_index: int = 255,
                     weight=None) -> np.ndarray:
    """``[num_classes, num_classes]`` float64 counts (or summed ``weight``) of
    (truth, prediction) pairs over the entries whose target is a class (not
    ``ignore_index``, not out of range). ``pred`` and ``target`` have one shape; ``weight``
    broadcasts to it."""
    p, t = np.asarray(pred).astype(np.int64).ravel(), np.asarray(target).astype(np.int64).ravel()
    if p.shape != t.shape:
        raise ValueError(f"pred and target differ in size: {np.shape(pred)} vs {np.shape(target)}")
    w = None if weight is None else np.broadcast_to(np.asarray(weight, np.float64),
                                                    np.shape(target)).ravel()
    if w is not None and not (np.isfinite(w) & (w >= 0)).all():
        raise ValueError("weight must be finite and >= 0 (a point's area)")
    keep = (t != ignore_index) & (t >= 0) & (t < num_classes)
    if ((p[keep] < 0) | (p[keep] >= num_classes)).any():
        raise ValueError(f"predictions must be class indices in [0, {num_classes})")
    idx = t[keep] * num_classes + p[keep]
    conf = np.bincount(idx, weights=None if w is None else w[keep], minlength=num_classes ** 2)
    return conf.reshape(num_classes, num_classes).astype(np.float64)


def _nan_mean(v: np.ndarray) -> float:
    return float(np.nanmean(v)) if np.isfinite(v).any() else float("nan")


def scores(conf: np.ndarray, names=None) -> dict:
    """mIoU, mAcc and overall accuracy (fractions), and per-class IoU/accuracy (NaN for a
    class absent from truth and predictions, or from the truth for accuracy)."""
    conf = np.asarray(conf, np.float64)
    tp = np.diag(conf)
    truth, predicted = conf.sum(1), conf.sum(0)
    union = truth + predicted - tp
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = np.where(union > 0, tp / union, np.nan)
        acc = np.where(truth > 0, tp / truth, np.nan)
    names = list(names) if names is not None else [str(c) for c in range(len(conf))]
    return {"mIoU": _nan_mean(iou), "mAcc": _nan_mean(acc),
            "acc": float(tp.sum() / max(conf.sum(), 1e-300)),
            "IoU": {n: None if np.isnan(v) else float(v) for n, v in zip(names, iou)},
            "Acc": {n: None if np.isnan(v) else float(v) for n, v in zip(names, acc)}}


def per_image_miou(confusions) -> float:
    """USF's variant: the mean over images of each image's mIoU (over the classes present
    in that image's truth or prediction). Not the standard metric; see the module docstring."""
    vals = [scores(c)["mIoU"] for c in confusions]
    vals = [v for v in vals if np.isfinite(v)]
    return float(np.mean(vals)) if vals else float("nan")


def score(pixels: np.ndarray, ds, points: np.ndarray | None = None) -> dict:
    """mIoU/mAcc (confusion over the test set) on the camera's pixels; with ``points``,
    also the area-weighted one on the grid (``sphere_mIoU``) and USF's per-image mean
    (``per_image_mIoU``, on pixels)."""
    C = len(SEMANTIC_CLASSES)
    truth = ds.label_image.numpy()
    sphere = None if points is None else \
        confusion_matrix(points, ds.y.numpy(), C, weight=ds.grid.area.numpy()[None])
    return score_confusions([confusion_matrix(p, t, C) for p, t in zip(pixels, truth)],
                            SEMANTIC_CLASSES, sphere)


def score_confusions(confusions, names, sphere: np.ndarray | None = None) -> dict:
    """:func:`scores` of the images' summed confusion matrices (``confusions``, one per
    image, on pixels), with USF's per-image mean (``per_image_mIoU``) and, given the
    area-weighted confusion on the grid ``sphere``, its mIoU (``sphere_mIoU``)."""
    res = scores(sum(confusions), names)
    res["per_image_mIoU"] = per_image_miou(confusions)
    if sphere is not None:
        res["sphere_mIoU"] = scores(sphere)["mIoU"]
    return res


def median_frequency_weights(counts) -> torch.Tensor:
    """Median frequency balancing (Eigen & Fergus): ``median(f) / f_c`` for class
    frequencies ``f`` (counts or areas) of the classes seen, the mean of the middle two for
    an even number of them; classes never seen get weight 0 (they have no loss terms)."""
    f = np.asarray(counts, np.float64)
    if not np.isfinite(f).all() or (f < 0).any() or f.sum() <= 0:
        raise ValueError("class counts must be finite and >= 0 with a positive total")
    seen = f > 0
    w = np.where(seen, np.median(f[seen]) / np.where(seen, f, 1.0), 0.0)
    return torch.from_numpy(w).float()


__all__ = ["confusion_matrix", "scores", "score", "score_confusions", "per_image_miou", "median_frequency_weights"]
