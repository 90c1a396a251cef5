"""Detection end to end: train on gravity-aligned panoramas, test rotated and through other lenses.

The protocol (:func:`run`) trains the spherical detector and the planar baseline on the
procedural rooms seen by an upright equirectangular camera, then scores both with COCO AP
(:func:`~usf_graph.train.det_metrics.coco_ap`) and USF's mAP@10 on (a) new rooms, same
camera; (b) the same views under Haar-random rotations; (c) the same views through a
190-degree fisheye; (d) through a 90-degree pinhole, both zero-shot. The planar baseline
sees (c) and (d) re-imaged as panoramas (black where the lens does not see). The spherical
detector ends with a second phase on parts of the panoramas, through random fields of view
(:class:`ThroughRandomFields`), its BatchNorm statistics frozen; the planar one trains as
long, on whole panoramas.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from ..geometry import geodesic_distance
from ..models import PlanarDetector, SphericalDetector
from ..models.centernet import box_centres, fields_on_cpu, nearest_points
from ..ops import box_iou
from ..scenes import DETECTION_CLASSES
from ..scenes.materials import check_materials
from .det_data import DetectionSet
from .det_metrics import coco_ap, usf_map
from .devices import model_device, resolve_device, setup_distributed, to_device
from .engine import (
    check_channel_scale,
    fit,
    save_checkpoint,
    scaled_channels,
    seed_everything,
    write_results,
)
from .fov import FOV_SHARE, FieldDraws, RandomFields, check_share, second_phase
from .gravity import (
    check_extra_rooms,
    given_up,
    known_up,
    pretrain_up,
    split_up,
    trains_up,
    up_loss,
    up_views,
    views_up,
)

PROTOCOL = {"a": ("equirectangular", "none"), "b": ("equirectangular", "so3"),
            "c": ("fisheye190", "none"), "d": ("pinhole90", "none")}
# the spherical detector's oriented convolutions: on the head's level (4) and coarser (README)
UPRIGHT_CONVS = 4
# every detector's second phase, the spherical one's through random fields of view (README)
FOV_EPOCHS = 6
#: Views per batch when a trained detector predicts a test split.
PREDICT_BATCH = 16
PROTOCOL_NAMES = {"a": "in distribution", "b": "SO(3)-rotated", "c": "fisheye 190 (zero-shot)",
                  "d": "pinhole 90 (zero-shot)"}


class ThroughRandomFields(FieldDraws):
    """A ``collate_fn`` over a spherical :class:`DetectionSet` that sees a share of the
    batches through one random field of view (:func:`~usf_graph.train.fov.random_field_of_view`,
    a pinhole's or a fisheye's, over the grid points ``pos [N, 3]``), with the boxes whose
    centre it hides left out: training on parts of the sphere, as narrower lenses show it.
    ``share``: the probability of a batch being cut; ``seed``: of the draws; ``camera``,
    ``turn``: cut through that camera's field of view instead, turned at random (as
    :class:`~usf_graph.train.fov.RandomFields`'s)."""

    def __init__(self, data: DetectionSet, pos: torch.Tensor, share: float = FOV_SHARE,
                 seed: int = 0, camera=None, turn: str = "yaw"):
        if pos.shape != (data.x.shape[1], 3):
            raise ValueError(f"pos must be the grid's points [{data.x.shape[1]}, 3], got {tuple(pos.shape)}")
        self.data, self.fields = data, RandomFields(pos, share, seed, camera, turn)

    def __call__(self, idx: list[int]):
        x, mask, boxes, classes, image = self.data.collate(idx)
        seen = self.fields(mask)
        if seen is None:
            return x, mask, boxes, classes, image
        keep = seen[nearest_points(boxes, self.fields.pos)]
        return x, seen, boxes[keep], classes[keep], image[keep]


def detection_step(model, batch):
    """The engine's step for detectors: their own ``loss`` on a :meth:`DetectionSet.collate`
    batch; a spherical detector with an up estimate learns it as the segmenters do
    (:mod:`~usf_graph.train.gravity`), on gravity-aligned views."""
    x, mask, boxes, classes, image = batch
    core = getattr(model, "module", model)  # under DistributedDataParallel
    if getattr(core, "gravity", None) is None:
        loss, stats = core.loss(model(x, mask), boxes, classes, image)
        return loss, stats, len(x)
    g, noisy = known_up(batch, x)  # views of the rooms protocol are upright
    out = model(x, mask, up=noisy)
    loss, stats = core.loss(out, boxes, classes, image)
    if trains_up(model):  # else pretrained and frozen: not run, no loss of its own
        loss = loss + up_loss(core.gravity.head, out["gravity"], g, stats)
    return loss, stats, len(x)


@torch.no_grad()
def predict(model, data: DetectionSet, batch_size: int = PREDICT_BATCH, progress: bool = True,
            desc: str = "detect", up: torch.Tensor | None = None, **decode) -> list[dict]:
    """Detections for every sample of ``data`` (see ``SphericalDetector.decode``); ``up
    [3]`` or ``[S, 3]``: the views' known gravity, read instead of the estimate
    (``gravity=True``; :func:`~usf_graph.train.gravity.views_up`). Runs on the device the
    model is on."""
    model.eval()
    out, dev = [], model_device(model)
    for s in tqdm(range(0, len(data), batch_size), desc=desc, leave=False, disable=not progress):
        x, mask, *_ = to_device(data.collate(list(range(s, min(s + batch_size, len(data))))), dev)
        out += model.decode(model(x, mask, **given_up(up, x, s)), **decode)
    return out


@torch.no_grad()
def box_quality(model, data: DetectionSet, batch_size: int = 16, progress: bool = True) -> dict:
    """How good a detector's boxes are where its heatmap is right: each true box is decoded
    from the fields at the output point nearest its centre, as if the heatmap had its one
    peak there (an oracle heatmap), and compared with the truth. This splits the AP's
    losses into finding objects (the heatmap) and drawing their boxes.

    Returns per true box (numpy): ``iou`` (with the predicted centre, size and axes),
    ``iou_true_centre`` (the predicted box moved onto the true centre), ``centre_deg``
    (the centre's error), ``log_size_err`` (of the mean log field of view
    ``(log fov_x + log fov_y) / 2``, which no choice of axes changes) and
    ``log_aspect_err`` (of ``|log fov_x - log fov_y| / 2``)."""
    model.eval()
    pts = getattr(model, "head_pos", None)
    pts = (model.points if pts is None else pts).cpu()
    dev = model_device(model)
    res = {k: [] for k in ("iou", "iou_true_centre", "centre_deg", "log_size_err", "log_aspect_err")}
    for s in tqdm(range(0, len(data), batch_size), desc="box quality", leave=False, disable=not progress):
        x, mask, boxes, classes, image = data.collate(list(range(s, min(s + batch_size, len(data)))))
        if not len(boxes):
            continue
        out = fields_on_cpu(model(*to_device((x, mask), dev)))
        boxes = boxes.double()
        near = nearest_points(boxes, pts)
        # one copy of the fields per true box, with a single peak at its centre point
        one = {k: v[image] if torch.is_tensor(v) and v.dim() > 1 else v for k, v in out.items()}
        heat = torch.full_like(one["heat"], -30.0)
        heat[torch.arange(len(boxes)), near, classes] = 30.0
        dec = model.decode({**one, "heat": heat, "mask": None}, k=1, threshold=0.5, nms=None,
                           drop_hidden=False)
        pred = torch.as_tensor(np.stack([d["boxes"][0] for d in dec]))
        moved = torch.cat([boxes[:, :2], pred[:, 2:]], 1)
        res["iou"].append(box_iou(pred, boxes))
        res["iou_true_centre"].append(box_iou(moved, boxes))
        res["centre_deg"].append(torch.rad2deg(geodesic_distance(box_centres(pred), box_centres(boxes))))
        lp, lt = pred[:, 2:4].log(), boxes[:, 2:4].log()
        res["log_size_err"].append((lp.mean(1) - lt.mean(1)).abs())
        res["log_aspect_err"].append(((lp[:, 0] - lp[:, 1]).abs() - (lt[:, 0] - lt[:, 1]).abs()).abs() / 2)
    return {k: torch.cat(v).numpy() if v else np.zeros(0) for k, v in res.items()}


def score(dets: list[dict], data: DetectionSet, num_classes: int) -> dict:
    """COCO AP/AP50/AP75 and AR50 (pycocotools, spherical IoU; :func:`coco_ap`), the true
    boxes the camera cuts ignored (:meth:`DetectionSet.ignored`), and USF's mAP@10 and
    mAP@50 on every true box, as USF counts them. ``AP50_every_box``: AP50 with no box
    ignored, the rule before session 35, for comparison with earlier tables."""
    truth = [data.truth(i) for i in range(len(data))]
    d = [(r["boxes"], r["classes"], r["scores"]) for r in dets]
    ignored = [data.ignored(i) for i in range(len(data))]
    res = coco_ap(truth, d, num_classes, ignored)
    every = res["AP50"] if not any(i.any() for i in ignored) else coco_ap(truth, d, num_classes)["AP50"]
    res.update({"AP50_every_box": every,
                "usf_mAP@10": usf_map(truth, d, num_classes, 0.10),
                "usf_mAP@50": usf_map(truth, d, num_classes, 0.50)})
    return res


def protocol_sets(root, size: int = 128, grid: str = "icosahedral:5", num_train: int = 200,
                  num_test: int = 50, seed: int = 0, progress: bool = True,
                  materials: str = "random", tests=tuple(PROTOCOL)) -> dict:
    """The rooms splits of the protocol: ``{"train": ..., "a": ..., "b": ..., "c": ..., "d": ...}``
    (no ``train`` when ``num_train`` is 0; the ``tests`` named), of rooms with ``materials``
    (:mod:`usf_graph.scenes.materials`)."""
    from ..datasets import RoomsDetection
    from ..scenes.lenses import protocol_cameras

    cams = protocol_cameras(size)
    kw = dict(grid=grid, seed=seed, progress=progress, materials=materials)
    sets = {} if not num_train else {"train": RoomsDetection(
        root, "train", camera=cams["equirectangular"], num_scenes=num_train, **kw)}
    for k in tests:
        cam, rot = PROTOCOL[k]
        sets[k] = RoomsDetection(root, "test", camera=cams[cam], rotate=rot, num_scenes=num_test, **kw)
    return sets


def make_detector(num_classes: int = len(DETECTION_CLASSES), upright: bool = True,
                  upright_convs: int | None = UPRIGHT_CONVS,
                  channel_scale: float = 1.0, gray: bool = False) -> SphericalDetector:
    """The protocols' spherical detector: with ``upright`` it reads an up estimate
    (``gravity=True``) and directions in its frame, with
    :class:`~usf_graph.nn.UprightConv` on the levels up to ``upright_convs``; every channel
    count times ``channel_scale`` (:func:`~usf_graph.train.engine.scaled_channels`);
    ``gray``: it reads only its input's luma (mono cameras)."""
    return SphericalDetector(num_classes=num_classes, gravity=upright, upright=upright, gray=gray,
                             upright_convs=upright_convs if upright else None,
                             **scaled_channels(SphericalDetector, channel_scale))


def run(root="data/rooms", out="runs/det", size: int = 128, num_train: int = 200,
        num_test: int = 50, epochs: int = 24, planar_epochs: int | None = None,
        batch_size: int = 8, lr: float = 2e-3, seed: int = 0, planar: bool = True,
        progress: bool = True, upright: bool = True, up_train: int = 400,
        up_epochs: int = 12, up_extra: int = 1600, up_caps: float = 0.5,
        upright_convs: int | None = UPRIGHT_CONVS, fov_epochs: int = FOV_EPOCHS,
        fov_share: float = FOV_SHARE, up_sign: float = 0.0, channel_scale: float = 1.0,
        resume: bool = False, device: str | None = None, materials: str = "random",
        gray: bool = False) -> dict:
    """The detection protocol on procedural rooms (module docstring). Writes
    ``results.json``, both checkpoints and ``det_results.png`` under ``out``.
    ``channel_scale``: both detectors' channel counts times this
    (:func:`~usf_graph.train.engine.scaled_channels`; the up estimate keeps its own).

    ``upright``: the spherical detector reads directions along its up estimate
    (``SphericalDetector(gravity=True, upright=True, upright_convs=upright_convs)``:
    :class:`~usf_graph.nn.UprightConv` on the levels up to ``upright_convs``, None for
    none); the estimate is trained first,
    alone, on the first ``up_train`` training views and ``up_extra`` cheap panoramas of
    other rooms (:class:`~usf_graph.datasets.RoomsGravity`, 96 pixels high, so that one
    render serves the segmentation protocol too) for ``up_epochs``, a share ``up_caps`` of
    its batches seen through random caps of 40-100 degrees, then frozen
    (:func:`~usf_graph.train.gravity.pretrain_up`; ``up_sign``: as
    :func:`usf_graph.train.seg.run`'s), and the detector trains on the first ``num_train``
    views, reading their known up.

    ``fov_epochs``: then each detector trains that many more epochs at learning rate
    ``FOV_LR`` (0: no second phase). The spherical one sees a share ``fov_share`` of its
    batches through random fields of view (:class:`ThroughRandomFields`), so that it also
    works from the part of the sphere a narrower lens sees. Its batch normalizations keep
    the panoramas' running statistics meanwhile
    (:func:`~usf_graph.train.engine.freeze_norms`), as every test view is normalized with
    them; with the statistics of parts of the sphere, or trained through fields of view
    from the start, it learns much less (README). The planar one, which has no field of
    view to cut, sees whole panoramas, so that both train as long.

    ``resume``: continue an interrupted run under ``out``, every stage from its ``last.pt``
    (:func:`~usf_graph.train.engine.fit`; finished ones just load). ``device``: where the
    detectors train and predict (:func:`~usf_graph.train.devices.resolve_device`; default
    the CPU). ``materials``: the rooms' (:mod:`usf_graph.scenes.materials`; ``"random"``,
    the protocol's). ``gray``: both detectors read only their views' luma (mono cameras;
    :func:`make_detector`), in training and in every test."""
    check_channel_scale(channel_scale)  # these before any rendering
    check_materials(materials)
    check_share(fov_share)
    check_extra_rooms(seed, up_extra if upright else 0)
    dev = resolve_device(device)
    rank, _ = setup_distributed()
    seed_everything(seed)
    out, t0 = Path(out), time.time()
    sets = protocol_sets(root, size, num_train=max(num_train, up_train if upright else 0),
                         num_test=num_test, seed=seed, progress=progress, materials=materials)
    C = len(DETECTION_CLASSES)
    results = {"samples": {"train": num_train, "test": num_test}, "size": size,
               "boxes": {k: int(len(d.boxes)) for k, d in sets.items() if k != "train"},
               "ignored_boxes": {},  # per test: cut by the camera's border (DetectionSet.ignored)
               "upright": upright, "fov_epochs": fov_epochs, "fov_share": fov_share,
               "up_sign": up_sign, "channel_scale": channel_scale, "materials": materials,
               "drop_hidden": True, "gray": gray}  # the decoding rule (c) and (d) were scored with
    spherical = make_detector(C, upright, upright_convs, channel_scale, gray).to(dev)
    if upright:
        results["samples"]["up_train"] = up_train
        results["samples"]["up_extra"] = up_extra
        pretrain_up(spherical, sets["train"][:up_train], up_epochs, batch_size, seed=seed,
                    progress=progress, log_dir=out / "up_estimate", caps=up_caps,
                    sign_weight=up_sign, extra=up_views(root, up_extra, progress=progress, materials=materials),
                    resume=resume)
    models = {"spherical": (spherical, DetectionSet.spherical, epochs)}
    if planar:
        w, h = 2 * size, size
        seed_everything(seed)  # the same initialization whatever the up estimate's training drew
        models["planar"] = (PlanarDetector(num_classes=C, height=h, width=w, gray=gray,
                                           **scaled_channels(PlanarDetector, channel_scale)).to(dev),
                            lambda ds: DetectionSet.planar(ds, w, h, progress), planar_epochs or epochs)
    preds, ignored = {}, {}
    for name, (net, make, ep) in models.items():
        data = {k: make(d) for k, d in sets.items()}
        data["train"] = data["train"].first(num_train)
        t = time.time()
        fit(net, data["train"], None, epochs=ep, batch_size=batch_size, lr=lr, seed=seed,
            log_dir=out / name, config=net.config, progress=progress, name=name,
            step=detection_step, collate_fn=data["train"].collate, resume=resume)
        if fov_epochs:  # the planar detector has no field of view to cut: whole panoramas
            cut = ThroughRandomFields(data["train"], sets["train"].grid.pos, fov_share, seed) \
                if name == "spherical" else None
            second_phase(net, data["train"], fov_epochs, out / name, name, cut=cut,
                         collate_fn=data["train"].collate, batch_size=batch_size, seed=seed,
                         config=net.config, progress=progress, step=detection_step, resume=resume)
        if rank != 0:
            continue
        results.setdefault("train_seconds", {})[name] = round(time.time() - t, 1)
        results[name], preds[name] = {}, {}
        for k in PROTOCOL:
            u = split_up(net, sets[k], batch_size=PREDICT_BATCH)  # once, for the boxes and the report
            preds[name][k] = predict(net, data[k], PREDICT_BATCH, progress=progress,
                                     desc=f"{name} ({k})", up=u.up)
            results[name][k] = score(preds[name][k], data[k], C)
            ignored[k] = data[k].ignored()
            results["ignored_boxes"][k] = int(ignored[k].sum())
            if u.estimate is not None:
                results[name][k]["up"] = u.report(views_up(sets[k]))
        save_checkpoint(out / f"{name}.pt", net, net.config, results[name],
                        extra={"data": {"dataset": "rooms", "seed": seed, "materials": materials}})
    if rank != 0:
        return {}
    from ..viz import plot_detections

    return write_results(out, results, t0, "det_results.png",
                         lambda p: plot_detections(sets, preds["spherical"], p, ignored=ignored),
                         resumed=resume)


def format_table(results: dict, metric: str = "AP50") -> str:
    """The protocol table in Markdown: ``metric`` (in points) per model and test."""
    rows = ["| model | " + " | ".join(f"({k}) {PROTOCOL_NAMES[k]}" for k in PROTOCOL) + " |",
            "|---" * (len(PROTOCOL) + 1) + "|"]
    for name in ("spherical", "planar"):
        if name in results:
            rows.append(f"| {name} | " + " | ".join(f"{100 * results[name][k][metric]:.1f}"
                                                     for k in PROTOCOL) + " |")
    return "\n".join(rows)
