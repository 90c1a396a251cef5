"""Training on the released datasets, which cannot be downloaded on our machines: the
folds of Stanford 2D-3D-S (segmentation, :func:`run_stanford`) and PANDORA (detection,
:func:`run_pandora`), each model trained by the rooms protocols' recipe. ``usf-graph
scenes --layout stanford2d3ds|pandora`` writes procedural rooms in their layouts, on which
these run offline. WoodScape's fisheyes (segmentation, :func:`run_woodscape`, scored by
:func:`evaluate_fields` on each image's own camera) train on fixtures in its layout in the
tests."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from ..scenes import PANDORA_CLASSES
from . import det, seg, seg_eval
from .devices import is_planar, model_device, resolve_device, setup_distributed
from .engine import (
    field_groups,
    fit,
    group_batches,
    save_checkpoint,
    seed_everything,
    write_results,
)
from .gravity import pretrain_up, views_up
from .seg_metrics import confusion_matrix, score, score_confusions, scores


def run_stanford(root="data/stanford2d3ds", out="runs/seg_stanford", folds=(1,),
                 models=("spherical_unet",), level: int = 5, size: int = 256, epochs: int = 12,
                 batch_size: int = 8, lr: float = 3e-3, seed: int = 0,
                 progress: bool = True, balance: float = 0.5, up_epochs: int = 24,
                 upright: bool = True, resume: bool = False, device: str | None = None,
                 gray: bool = False) -> dict:
    """Train on each fold's training areas of Stanford 2D-3D-S (RGB, unrotated as released)
    and score its test areas: mIoU and mAcc from the fold's confusion matrix on the
    ``2 size x size`` panoramas' pixels, the sphere's area-weighted mIoU, and USF's per-image
    mean. With several folds, also their mean (the usual 3-fold number). Writes
    ``results.json`` and one checkpoint per fold and model under ``out``. Each model is
    trained as in the rooms protocol (:func:`~usf_graph.train.seg.train_model`: class
    weights, the up estimate first, per fold; ``upright`` as
    :func:`~usf_graph.train.seg.make_model`'s; ``resume``, ``device`` and ``gray`` as
    :func:`~usf_graph.train.seg.run`'s)."""
    from ..datasets import Stanford2D3DS

    dev = resolve_device(device)
    rank, _ = setup_distributed()
    seg.check_models(models, level)
    seed_everything(seed)
    out, t0 = Path(out), time.time()
    kw = dict(grid=f"icosahedral:{level}", size=size, progress=progress)
    results = {"folds": list(folds), "level": level, "size": size, "epochs": epochs,
               "balance": balance, "up_epochs": up_epochs, "upright": upright, "gray": gray}
    for fold in folds:
        train = Stanford2D3DS(root, fold, "train", **kw)
        test = Stanford2D3DS(root, fold, "test", **kw)
        shared = {}
        for name in models:
            net = seg.make_model(name, level, upright, gray=gray).to(dev)
            seg.train_model(net, train, out / f"fold{fold}", name, epochs, batch_size, lr, seed,
                        progress, balance, up_epochs, shared, label=f"{name} fold {fold}",
                        resume=resume)
            if rank != 0:
                continue
            pix, pts = seg_eval.predict(net, test, progress=progress, desc=f"{name} fold {fold}")
            r = results.setdefault(name, {})[f"fold{fold}"] = score(pix, test, pts)
            save_checkpoint(out / f"fold{fold}_{name}.pt", net, {"model": name, "size": size, **net.config},
                            r, extra={"data": {"dataset": "stanford2d3ds", "fold": fold}})
    if rank != 0:
        return {}
    for name in models:
        per = [results[name][f"fold{f}"] for f in folds]
        results[name]["mean"] = {m: float(np.mean([r[m] for r in per]))
                                 for m in ("mIoU", "mAcc", "sphere_mIoU", "per_image_mIoU")
                                 if all(m in r for r in per)}
    return write_results(out, results, t0, resumed=resume)


@torch.no_grad()
def evaluate_fields(model, ds, known_up: bool = True, batch_size: int = seg_eval.PREDICT_BATCH,
                    progress: bool = True, desc: str = "segment", render: str = "nearest",
                    names=None) -> dict:
    """Scores of a spherical model on a split whose samples have cameras of their own
    (``ds.x [S, N, C]``, ``ds.y``, ``ds.mask [S, N]``, ``ds.frontend(i)`` and
    ``ds.label_image(i)``, e.g. :class:`~usf_graph.datasets.WoodScape`): batched by field
    of view (:func:`~usf_graph.train.engine.field_groups`), each sample's predictions
    rendered into its own camera's pixels (``render``: as :func:`~usf_graph.train.seg_eval.predict`'s) and scored there
    (:func:`~usf_graph.train.seg_metrics.score_confusions`: mIoU and mAcc over the split,
    USF's per-image mean, the sphere's area-weighted mIoU), with the mIoU of each camera
    (``ds.camera_names``) under ``"cameras"``. ``known_up``: the model reads the views'
    gravity (``ds.gravity``), else its estimate. ``names``: the classes (default: their
    indices)."""
    if is_planar(model):
        raise ValueError("evaluate_fields scores spherical models; a planar one has no grid")
    model.eval()
    dev, C = model_device(model), model.config["num_classes"]
    up, area = (views_up(ds) if known_up else None), ds.grid.area.numpy()[None]
    confs, sphere = [None] * len(ds), np.zeros((C, C))
    batches = group_batches(field_groups(ds.mask), batch_size, shuffle=False)
    for b in tqdm(batches, desc=desc, leave=False, disable=not progress):
        x, mask = ds.x[b].to(dev).float(), ds.mask[b[0]]
        mask = None if mask.all() else mask.to(dev)
        logits = model(x, mask, **({} if up is None else {"up": up[b].to(dev, x.dtype)})).cpu()
        for i, lg in zip(b, logits):
            sphere += confusion_matrix(lg.argmax(-1).numpy()[None], ds.y[i].numpy()[None], C,
                                       weight=area)
            pixels = ds.frontend(i).to_labels(lg.softmax(-1) if render == "soft" else lg, render)
            confs[i] = confusion_matrix(pixels.numpy(), ds.label_image(i), C)
    names = list(names) if names is not None else [str(c) for c in range(C)]
    res = score_confusions(confs, names, sphere)
    cams = list(getattr(ds, "camera_names", ["all"] * len(ds)))
    res["cameras"] = {c: scores(sum(f for f, k in zip(confs, cams) if k == c), names)["mIoU"]
                      for c in dict.fromkeys(cams)}
    return res


def run_woodscape(root="data/woodscape", out="runs/seg_woodscape",
                  models=("spherical_deeplab",), level: int = 5, scale: float = 0.5,
                  epochs: int = 12, batch_size: int = 8, lr: float = 3e-3, seed: int = 0,
                  progress: bool = True, balance: float = 0.5, upright: bool = True,
                  up_epochs: int = 0, known_up: bool = True, resume: bool = False,
                  device: str | None = None, gray: bool = False) -> dict:
    """Train on WoodScape's ``train`` list (OmniDet's) and score its ``val`` list: every image
    lifted through its own calibration (:class:`~usf_graph.datasets.WoodScape`, images
    resized by ``scale``), the four cameras' images in one training set, each batch from one
    field of view (:func:`~usf_graph.train.engine.field_groups`). Scores are on each image's
    own pixels (:func:`evaluate_fields`): mIoU and mAcc over the
    split's confusion matrix on the 10 classes, void included, as OmniDet counts them, the
    sphere's area-weighted mIoU, and each camera's mIoU. Spherical models only (a planar
    one would train on the fisheye images; WoodScape's own baselines do that).

    The up estimate trains with the segmenter (``up_epochs=0``), or first and alone for
    ``up_epochs`` on the same images (:func:`~usf_graph.train.seg.train_model`), batched
    by field of view as well. ``known_up``: at test, the models read the vehicle frame's up (+z, the road's slope
    aside), where every calibration places its camera, as they would read an IMU; else
    their estimate. Writes ``results.json`` and ``<model>.pt`` under ``out``; ``resume``,
    ``device`` and ``gray`` as :func:`~usf_graph.train.seg.run`'s."""
    from ..datasets import WoodScape
    from ..datasets.woodscape import CLASSES

    if planar := [m for m in models if m not in ("spherical_unet", "spherical_deeplab")]:
        raise ValueError(f"WoodScape trains the spherical models (spherical_unet, "
                         f"spherical_deeplab), not {planar}")
    seg.check_models(models, level)
    dev = resolve_device(device)
    rank, _ = setup_distributed()
    seed_everything(seed)
    out, t0 = Path(out), time.time()
    kw = dict(grid=f"icosahedral:{level}", scale=scale, progress=progress)
    train, test = WoodScape(root, "train", **kw), WoodScape(root, "val", **kw)
    groups = field_groups(train.mask)
    results = {"samples": {"train": len(train), "test": len(test)}, "fields_of_view": int(groups.max()) + 1,
               "level": level, "scale": scale, "epochs": epochs, "balance": balance,
               "upright": upright, "up_epochs": up_epochs, "known_up": known_up, "gray": gray}
    shared = {}
    for name in models:
        seed_everything(seed)
        net = seg.make_model(name, level, upright, gray=gray, num_classes=len(CLASSES)).to(dev)
        seg.train_model(net, train, out, name, epochs, batch_size, lr, seed, progress, balance,
                        up_epochs, shared, resume=resume, groups=groups)
        if rank != 0:
            continue
        results[name] = r = evaluate_fields(net, test, known_up, progress=progress,
                                                desc=f"{name} val", names=CLASSES)
        save_checkpoint(out / f"{name}.pt", net, {"model": name, **net.config}, r,
                        extra={"data": {"dataset": "woodscape", "scale": scale}})
    if rank != 0:
        return {}
    return write_results(out, results, t0, resumed=resume)


def run_pandora(root="data/pandora", out="runs/det_pandora", epochs: int = 24,
                batch_size: int = 8, lr: float = 2e-3, seed: int = 0, grid: str = "icosahedral:5",
                progress: bool = True, upright: bool = True, up_epochs: int = 24,
                resume: bool = False, device: str | None = None, gray: bool = False) -> dict:
    """Train the spherical detector on PANDORA's train split (unrotated, as released) and
    score its test split: COCO AP/AP50/AP75 with the spherical IoU and USF's mAP@10.
    Writes ``results.json`` and ``spherical.pt`` under ``out``. ``upright``: as in
    :func:`~usf_graph.train.det.run`, the up estimate trained first on the same panoramas;
    ``resume``, ``device`` and ``gray`` as its."""
    from ..datasets import Pandora

    dev = resolve_device(device)
    rank, _ = setup_distributed()
    seed_everything(seed)
    out, t0 = Path(out), time.time()
    train_set = Pandora(root, "train", grid=grid, progress=progress)
    train = det.DetectionSet.spherical(train_set)
    test = det.DetectionSet.spherical(Pandora(root, "test", grid=grid, progress=progress))
    C = len(PANDORA_CLASSES)
    net = det.make_detector(C, upright, gray=gray).to(dev)
    if upright:
        pretrain_up(net, train_set, up_epochs, batch_size, seed=seed, progress=progress,
                    log_dir=out / "up_estimate", resume=resume)
    fit(net, train, None, epochs=epochs, batch_size=batch_size, lr=lr, seed=seed,
        log_dir=out / "spherical", config=net.config, progress=progress, name="spherical",
        step=det.detection_step, collate_fn=train.collate, resume=resume)
    if rank != 0:
        return {}
    res = {"samples": {"train": len(train), "test": len(test)}, "gray": gray,
           "spherical": det.score(det.predict(net, test, progress=progress), test, C)}
    save_checkpoint(out / "spherical.pt", net, net.config, res["spherical"],
                    extra={"data": {"dataset": "pandora"}})
    return write_results(out, res, t0, resumed=resume)
