"""Scoring trained segmenters: per-pixel predictions in any camera's pixels, and the
protocol's tests (the rooms' :data:`PROTOCOL`; :mod:`usf_graph.train.seg` trains).

Spherical predictions reach the pixels through :meth:`SphericalFrontend.to_labels`
(nearest, the protocols'); a planar model sees other lenses re-imaged as a panorama and
its predictions are rendered back. Scores: :func:`~usf_graph.train.seg_metrics.score`.
"""

from __future__ import annotations

import numpy as np
import torch
from tqdm.auto import tqdm

from ..cameras import Equirectangular
from ..frontend import render as reimage
from .devices import is_planar, model_device
from .gravity import given_up, split_mask, split_up, views_up
from .seg_metrics import score

#: The protocol's tests: camera (:func:`~usf_graph.scenes.lenses.protocol_cameras`),
#: rotation, and how many grid levels (and doublings of size) finer than training.
PROTOCOL = {"a": ("equirectangular", "none", 0), "b": ("equirectangular", "so3", 0),
            "c": ("fisheye190", "none", 0), "d": ("pinhole90", "none", 0),
            "e": ("equirectangular", "none", 1)}
PROTOCOL_NAMES = {"a": "in distribution", "b": "SO(3)-rotated", "c": "fisheye 190 (zero-shot)",
                  "d": "pinhole 90 (zero-shot)", "e": "finer grid (zero-shot)"}
#: Views per batch when a trained model predicts a test split.
PREDICT_BATCH = 8


@torch.no_grad()
def predict(model, ds, batch_size: int = PREDICT_BATCH, progress: bool = True, desc: str = "segment",
            pano: Equirectangular | None = None, up: torch.Tensor | None = None,
            render: str = "nearest"):
    """Per-pixel class predictions ``[S, H, W]`` (uint8) in ``ds.camera``'s pixels, and for
    spherical models the per-point ones ``[S, N]`` (else ``None``). A planar model sees
    other lenses re-imaged as ``pano`` (default: ``2 H x H`` for the camera's height H,
    the protocol's training size). ``up [3]`` or ``[S, 3]``: the up each view is read
    with by a spherical model with ``gravity=True``, instead of running its estimate: the
    views' known gravity (an IMU; :func:`~usf_graph.train.gravity.views_up`) or an estimate
    already made (:func:`~usf_graph.train.gravity.split_up`). ``render``: how a spherical
    model's predictions reach the pixels (:meth:`SphericalFrontend.to_labels`: ``nearest``,
    the protocols', or ``soft``). Runs on the device the model is on."""
    model.eval()
    cam, S, dev = ds.camera, len(ds), model_device(model)
    pixels, points = [], []
    if is_planar(model):
        if isinstance(cam, Equirectangular):
            pano = cam
        elif pano is None:
            pano = Equirectangular(2 * cam.height, cam.height)
        for s in tqdm(range(0, S, batch_size), desc=desc, leave=False, disable=not progress):
            imgs = ds.image[s:s + batch_size].numpy()
            if pano is not cam:
                imgs = np.stack([reimage(im, cam, pano) for im in imgs])
            x = torch.as_tensor(imgs).permute(0, 3, 1, 2).to(dev).float() / 255
            pred = model(x).argmax(1).to(torch.uint8).cpu().numpy()
            if pano is not cam:
                pred = np.stack([reimage(p, pano, cam, interpolation="nearest") for p in pred])
            pixels.append(pred)
        return np.concatenate(pixels), None
    mask = split_mask(ds)
    mask = None if mask is None or mask.all() else mask.to(dev)
    for s in tqdm(range(0, S, batch_size), desc=desc, leave=False, disable=not progress):
        x = ds.x[s:s + batch_size].to(dev).float()
        logits = model(x, mask, **given_up(up, x, s)).cpu()
        points.append(logits.argmax(-1).to(torch.uint8))
        probs = logits.softmax(-1) if render == "soft" else logits  # blend probabilities
        pixels += [ds.frontend.to_labels(p, render).to(torch.uint8).numpy() for p in probs]
    return np.stack(pixels), torch.cat(points).numpy()


def evaluate_protocol(net, sets: dict, tests=tuple(PROTOCOL), progress: bool = True,
                      name: str = "model", known_up: bool = False,
                      up_lines: bool = False, render: str = "nearest") -> tuple[dict, dict]:
    """Scores and pixel predictions of one trained model on the protocol's test sets;
    ``known_up``, ``up_lines``, ``render``: as :func:`evaluate_set`'s. A model with an up estimate also
    gets its :func:`~usf_graph.train.gravity.up_summary` per test (``"up"``)."""
    res, preds = {}, {}
    for k in tests:
        model = net
        if not is_planar(net) and PROTOCOL[k][2]:
            model = net.refined(PROTOCOL[k][2])
        res[k], preds[k] = evaluate_set(model, sets[k], f"{name} ({k})", known_up, progress, up_lines,
                                        render)
    return res, preds


def evaluate_set(model, ds, desc: str = "segment", known_up: bool = False,
                 progress: bool = True, up_lines: bool = False,
                 render: str = "nearest", pano: Equirectangular | None = None
                 ) -> tuple[dict, np.ndarray]:
    """:func:`score` and the pixel predictions of a trained model on one test set (a rooms
    test or :class:`~usf_graph.datasets.Stanford2D3DS`); ``known_up``: a spherical model
    reads the views' gravity (:func:`views_up`); ``up_lines``: its up estimate picks among the
    straight-line axes of each image (:func:`~usf_graph.train.gravity.lines_up`). A model
    with an up estimate also gets its :func:`~usf_graph.train.gravity.up_summary` (``"up"``;
    the estimate runs once, for the prediction and the report). ``render``, ``pano``: as
    :func:`predict`'s."""
    u = split_up(model, ds, known_up, up_lines, batch_size=PREDICT_BATCH)
    pix, pts = predict(model, ds, PREDICT_BATCH, progress=progress, desc=desc, up=u.up,
                       render=render, pano=pano)
    r = score(pix, ds, pts)
    if u.estimate is not None:
        r["up"] = u.report(views_up(ds))
    return r, pix
