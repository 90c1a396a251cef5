"""Semantic segmentation end to end: train on gravity-aligned panoramas, test rotated,
through other lenses and on a finer grid.

The protocol (:func:`run`) trains the spherical U-Net, the spherical DeepLab v3 and the
planar U-Net on procedural rooms seen by an upright equirectangular camera, straight from
the PyG dataset (:class:`~usf_graph.datasets.RoomsSegmentation`) through the shared
engine (8 epochs, then a second phase of 6 at a lower learning rate, the spherical models'
through random fields of view: :func:`train_model`), then scores them
(:mod:`~usf_graph.train.seg_eval`, :mod:`~usf_graph.train.seg_metrics`) on:

(a) new rooms, same camera; (b) the same views under Haar-random rotations; (c) the same
views through a 190-degree fisheye; (d) through a 90-degree pinhole, both zero-shot;
(e) resolution transfer: panoramas at twice the size, lifted to the next finer grid (the
spherical models run there with the same weights, :meth:`SphericalUNet.refined`; the
planar one on the larger image).

Scores are on each camera's own pixels at its size (spherical predictions are rendered
back with :meth:`SphericalFrontend.to_image`, nearest), counting only the pixels it sees;
the spherical models are also scored on the grid, area-weighted (``sphere_mIoU``). The
planar model sees fisheye and pinhole images re-imaged as panoramas (black where the lens
does not see), and its predictions are rendered back into their pixels.
"""

from __future__ import annotations

import math
import time
from functools import partial
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..models import PlanarUNet, SphericalDeepLabV3, SphericalUNet
from ..nn.batching import to_static
from ..scenes import IGNORE, SEMANTIC_CLASSES
from ..scenes.materials import check_materials
from .devices import is_planar, resolve_device, setup_distributed
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
    known_up,
    pretrain_up,
    trains_up,
    up_loss,
    up_views,
)
from .seg_eval import PROTOCOL, PROTOCOL_NAMES, evaluate_protocol
from .seg_metrics import median_frequency_weights

# every model's second phase, the spherical ones' through random fields of view (README)
FOV_EPOCHS = 6
MODELS = {"spherical_unet": SphericalUNet, "spherical_deeplab": SphericalDeepLabV3,
          "planar_unet": PlanarUNet}


def segmentation_loss(logits: torch.Tensor, target: torch.Tensor, ignore_index: int = IGNORE,
                      class_weight: torch.Tensor | None = None,
                      point_weight: torch.Tensor | None = None) -> torch.Tensor:
    r"""Cross-entropy over the entries whose target is not ``ignore_index``, with optional
    ``class_weight [C]`` (e.g. :func:`median_frequency_weights`) and ``point_weight``
    (e.g. grid areas ``[N]``, broadcast to the target): :math:`\sum w_i \ell_i / \sum w_i`.

    ``logits [B, N, C]`` (points) or ``[B, C, H, W]`` (pixels) with ``target [B, N]`` or
    ``[B, H, W]``."""
    if logits.dim() == 3:
        logits = logits.transpose(1, 2)
    if not torch.isfinite(logits).all():
        raise ValueError("the model produced NaN or inf logits; lower the learning rate or "
                         "check the inputs")
    C = logits.shape[1]
    bad = (target != ignore_index) & ((target < 0) | (target >= C))
    if bool(bad.any()):  # cross_entropy's own error is an IndexError, a device assert on a GPU
        raise ValueError(f"labels must be class indices in [0, {C}) or {ignore_index} (ignored); "
                         f"found {sorted(set(target[bad].unique().tolist()))[:10]}: is the "
                         "dataset's label space the model's?")
    cw = None if class_weight is None else class_weight.to(logits.device, logits.dtype)
    loss = nn.functional.cross_entropy(logits, target, ignore_index=ignore_index, reduction="none")
    keep = (target != ignore_index).to(logits.dtype)
    w = keep if cw is None else keep * cw[target.clamp(0, len(cw) - 1)]
    if point_weight is not None:
        w = w * point_weight.to(logits.device, logits.dtype)
    return (loss * w).sum() / w.sum().clamp_min(1e-12)


def split_batch(batch):
    """A PyG batch of :class:`~usf_graph.datasets.RoomsSegmentation` samples ->
    ``(x [B, N, C], y [B, N], mask [N] or None, image [B, 3, H, W], label_image [B, H, W])``
    (the last two ``None`` for samples without images, e.g. :class:`~usf_graph.datasets.WoodScape`'s)."""
    B = batch.num_graphs
    x, _ = to_static(batch.x, batch.x.shape[0] // B, batch.batch, "segmentation batch")
    y = batch.y.view(B, -1)
    mask = batch.mask.view(B, -1)
    if not (mask == mask[0]).all():
        raise ValueError("the samples of a batch have different fields of view; batch one camera "
                         "(fit's groups=field_groups(dataset.mask))")
    if getattr(batch, "image", None) is None:
        return x, y, None if mask[0].all() else mask[0], None, None
    image = batch.image.permute(0, 3, 1, 2).float() / 255
    return x, y, None if mask[0].all() else mask[0], image, batch.label_image.long()


class ThroughRandomFields(FieldDraws):
    """A ``collate_fn`` over a spherical segmentation dataset (PyG samples with ``x``,
    ``y`` and ``mask``, e.g. :class:`~usf_graph.datasets.RoomsSegmentation`) that sees a
    share of the batches through one random field of view
    (:class:`~usf_graph.train.fov.RandomFields`, a pinhole's or a fisheye's, over the
    grid points ``pos [N, 3]``), its labels outside ignored: training on parts of the
    sphere, as narrower lenses show it. ``share``: the probability of a batch being cut;
    ``seed``: of the draws; ``camera``, ``turn``: cut through that camera's field of view
    instead, turned at random (as :class:`~usf_graph.train.fov.RandomFields`'s). Returns a
    :class:`~torch_geometric.data.Batch`."""

    def __init__(self, pos: torch.Tensor, share: float = FOV_SHARE, seed: int = 0,
                 camera=None, turn: str = "yaw"):
        self.fields = RandomFields(pos, share, seed, camera, turn)

    def __call__(self, samples: list):
        from torch_geometric.data import Batch

        batch = Batch.from_data_list(samples)
        if batch.mask.numel() != len(samples) * len(self.fields.pos):
            raise ValueError(f"the samples are not on the {len(self.fields.pos)} points this "
                             "collate_fn was built for")
        seen = self.fields(samples[0].mask)
        if seen is not None:
            batch.mask = seen.repeat(len(samples))
            batch.y = torch.where(batch.mask, batch.y, torch.full_like(batch.y, IGNORE))
        return batch


def segmentation_step(model, batch, class_weight: torch.Tensor | None = None):
    """The engine's step for segmentation, on PyG batches: per-point cross-entropy for
    spherical models, per-pixel for planar ones (which read the batch's ``image``).

    A spherical model with a gravity head learns up from the views' known gravity g (the
    batch's ``up [B, 3]`` when it has one, else +z: gravity-aligned views): its head is
    trained by :func:`~usf_graph.train.gravity.up_loss`, while the network reads the heights
    along g, jittered (:func:`~usf_graph.train.gravity.known_up`), so that the two learn
    independently; once :func:`~usf_graph.train.gravity.pretrain_up` has trained and
    frozen the up estimate, the step only reads the jittered g. At test time the network
    reads the estimate. ``class_weight [C]``: as :func:`segmentation_loss`'s (bind it with
    ``functools.partial``)."""
    x, y, mask, image, label = split_batch(batch)
    planar, stats, aux = is_planar(model), {}, 0.0
    net = getattr(model, "module", model)
    if planar and image is None:
        raise ValueError("a planar model trains on images, and these samples have none: train a "
                         "spherical model")
    if planar:
        logits, target = model(image), label
    elif trains_up(model):
        g, noisy = known_up(batch, x)
        (logits, grav), target = model(x, mask, up=noisy, return_gravity=True), y
        aux = up_loss(net.gravity.head, grav, g, stats)
    elif getattr(net, "gravity", None) is not None:
        logits, target = model(x, mask, up=known_up(batch, x)[1]), y
    else:
        logits, target = model(x, mask), y
    loss = segmentation_loss(logits, target, class_weight=class_weight) + aux
    pred = logits.argmax(1 if planar else -1)
    keep = target != IGNORE
    acc = (pred[keep] == target[keep]).double().mean().item() if keep.any() else 0.0
    return loss, {"acc": acc, **stats}, len(x)


def protocol_sets(root, size: int = 96, level: int = 5, num_train: int = 200,
                  num_test: int = 50, seed: int = 0, tests=tuple(PROTOCOL),
                  progress: bool = True, materials: str = "random") -> dict:
    """The rooms splits of the protocol, ``{"train": ..., "a": ..., ..., "e": ...}``
    (no ``train`` when ``num_train`` is 0): panoramas ``2 size x size`` on
    ``icosahedral:level`` (twice the size and one level finer for (e)), of rooms with
    ``materials`` (:mod:`usf_graph.scenes.materials`)."""
    from ..datasets import RoomsSegmentation
    from ..scenes.lenses import protocol_cameras

    kw = dict(seed=seed, progress=progress, materials=materials)
    sets = {} if not num_train else {"train": RoomsSegmentation(
        root, "train", camera=protocol_cameras(size)["equirectangular"],
        grid=f"icosahedral:{level}", num_scenes=num_train, **kw)}
    for k in tests:
        cam, rot, finer = PROTOCOL[k]
        sets[k] = RoomsSegmentation(root, "test", camera=protocol_cameras(size * 2 ** finer)[cam],
                                    grid=f"icosahedral:{level + finer}", rotate=rot,
                                    num_scenes=num_test, **kw)
    return sets


#: the coarsest input level of the spherical models (the U-Net pools three times)
MIN_LEVEL = 3


def check_models(models, level: int) -> None:
    """Refuse, before any data is read, a protocol's ``models`` that it cannot train on
    ``icosahedral:level``: none, an unknown name, or a spherical model below
    :data:`MIN_LEVEL`."""
    if not models:
        raise ValueError(f"no models to train: name at least one of {sorted(MODELS)}")
    if unknown := sorted(set(models) - set(MODELS)):
        raise ValueError(f"unknown models {unknown}: choose from {sorted(MODELS)}")
    if level < MIN_LEVEL and any(m != "planar_unet" for m in models):
        raise ValueError(f"level {level}: the spherical models need icosahedral:{MIN_LEVEL} or "
                         f"finer (the U-Net pools three times); give a level of at least {MIN_LEVEL}")


def make_model(name: str, level: int = 5, upright: bool = True,
               channel_scale: float = 1.0, gray: bool = False,
               num_classes: int = len(SEMANTIC_CLASSES)) -> nn.Module:
    """A protocol model by name (:data:`MODELS`), spherical ones on ``icosahedral:level``
    with their up estimate (``gravity=True``: trained on the views' known gravity, it
    gives the network each point's height, which a planar network reads from its rows)
    and, with ``upright``, derivatives along and across up (``upright=True``: the
    orientation a planar network's filters see); the DeepLab's stages on every level
    coarser than the input's then have oriented kernels as well
    (:class:`~usf_graph.nn.UprightConv`, ``upright_convs=level - 1``). ``channel_scale``:
    every channel count times this (:func:`~usf_graph.train.engine.scaled_channels`; the
    up estimate keeps its own). ``gray``: the model reads only its input's luma (for mono
    cameras; :class:`~usf_graph.models.upnet.WithUp`). ``num_classes``: the rooms' 13 by
    default."""
    check_models([name], level)
    C = num_classes
    widths = scaled_channels(MODELS[name], channel_scale)
    if name == "planar_unet":
        return PlanarUNet(C, gray=gray, **widths)
    # upright: oriented fields replace the gradient pairs, for the 2x step budget (README)
    kw = dict(upright=True, pairs=0, up_fields=4, **widths) if upright else widths
    if upright and name == "spherical_deeplab":  # the U-Net's stay distance-only: its step budget
        kw["upright_convs"] = level - 1
    return MODELS[name](C, level=level, gravity=True, gray=gray, **kw)


def balanced_weights(train, power: float = 0.5, num_classes: int = len(SEMANTIC_CLASSES)):
    """Class weights from a training set's labels: median-frequency balancing
    (:func:`median_frequency_weights`) raised to ``power`` (0: none, 1: full); ``None``
    for power 0."""
    if not power:
        return None
    y = train.y.reshape(-1).numpy()
    counts = np.bincount(y[y < num_classes], minlength=num_classes)
    return median_frequency_weights(counts) ** power


def train_model(net, train, out: Path, name: str, epochs: int, batch_size: int, lr: float,
                seed: int, progress: bool, balance: float, up_epochs: int, shared: dict,
                label: str | None = None, up_kw: dict | None = None, fov_epochs: int = 0,
                fov_share: float = FOV_SHARE, resume: bool = False, groups=None) -> None:
    """The protocols' recipe for one model on ``train``, logging under ``out / name``:
    class weights ``balance`` (:func:`balanced_weights`); for a spherical model first the up
    estimate, trained alone for ``up_epochs`` on the first use (under ``out /
    "up_estimate"``), kept in ``shared`` for the next models and frozen
    (:func:`~usf_graph.train.gravity.pretrain_up`; ``up_epochs=0``: trained with the
    segmenter instead; ``up_kw``: more of its keyword arguments). ``label``: the progress
    bars' name (default ``name``).

    ``fov_epochs``: the model then trains that many more epochs at ``FOV_LR`` (logging
    under ``out / name / "second_phase"``): a spherical one with a share ``fov_share`` of
    its batches seen through random fields of view (:class:`ThroughRandomFields`), its
    normalizations frozen (:func:`~usf_graph.train.engine.freeze_norms`: a cut batch's
    statistics are those of one part of one room); a planar one, which has no field of
    view to cut, on the whole panoramas, so that every model trains as long.

    ``resume``: every stage continues from its ``last.pt``
    (:func:`~usf_graph.train.engine.fit`). ``groups``: every stage batches within them (as
    ``fit``'s: a split of several cameras' fields of view), and there is no second phase,
    which cuts one field of view per batch."""
    if groups is not None and fov_epochs:
        raise ValueError("batches grouped by field of view have no second phase through "
                         "random fields of view (fov_epochs=0)")
    if getattr(net, "gravity", None) is not None and up_epochs:
        if "up" not in shared:
            pretrain_up(net, train, up_epochs, batch_size, lr, seed, progress,
                        log_dir=out / "up_estimate", resume=resume, groups=groups, **(up_kw or {}))
            shared["up"] = net.gravity.state_dict()
        net.gravity.load_state_dict(shared["up"])
        net.gravity.requires_grad_(False)
    weights = balanced_weights(train, balance, net.config.get("num_classes", len(SEMANTIC_CLASSES)))
    step = partial(segmentation_step, class_weight=weights)
    fit(net, train, None, epochs=epochs, batch_size=batch_size, lr=lr, seed=seed,
        log_dir=out / name, config=net.config, progress=progress, name=label or name, step=step,
        resume=resume, groups=groups)
    if fov_epochs:
        cut = None if is_planar(net) else ThroughRandomFields(train.grid.pos, fov_share, seed)
        second_phase(net, train, fov_epochs, out / name, label or name, cut=cut,
                     batch_size=batch_size, seed=seed, config=net.config, progress=progress,
                     step=step, resume=resume)


def run(root="data/rooms", out="runs/seg", size: int = 96, level: int = 5,
        num_train: int = 400, num_test: int = 50, epochs: int = 8, batch_size: int = 8,
        lr: float = 3e-3, seed: int = 0, models=tuple(MODELS), progress: bool = True,
        balance: float = 0.5, up_epochs: int = 8, upright: bool = True, up_extra: int = 800,
        up_caps: float = 0.5, fov_epochs: int = FOV_EPOCHS, fov_share: float = FOV_SHARE,
        up_sign: float = 0.0, channel_scale: float = 1.0, resume: bool = False,
        device: str | None = None, materials: str = "random", gray: bool = False) -> dict:
    """The segmentation protocol on procedural rooms (module docstring). Writes
    ``results.json``, one checkpoint per model and ``seg_results.png`` under ``out``.
    ``upright``, ``channel_scale``: as :func:`make_model`'s, for every model (0.5, with
    fewer epochs, is the README's 15-minute recipe).

    ``balance``: the class weights' power (:func:`balanced_weights`), for every model.
    ``up_epochs``: epochs of the spherical models' up estimate, trained once alone
    (:func:`~usf_graph.train.gravity.pretrain_up`) and shared (0: trained with the
    segmenter instead). It sees the training views and ``up_extra`` cheap panoramas of
    other rooms (:class:`~usf_graph.datasets.RoomsGravity`), a share ``up_caps`` of its
    batches through random caps (fewer than :func:`usf_graph.train.det.run`'s 1,600 x 12
    epochs, for time; README), and ``up_sign``: the weight of a penalty on scoring down
    above up (:meth:`~usf_graph.models.GravityHead.loss`'s ``sign_weight``; 0, the
    protocol's; 1 was a lead in session 26, docs/seg_det_log.md). Every model starts from
    the same seed, whatever the models before it drew. ``fov_epochs``, ``fov_share``: every model's
    second phase, the spherical ones' through random fields of view (:func:`train_model`;
    0 skips it). ``resume``: continue an interrupted run under ``out``, every stage from
    its ``last.pt`` (:func:`~usf_graph.train.engine.fit`; finished ones just load).
    ``device``: where the models train and predict
    (:func:`~usf_graph.train.devices.resolve_device`; default the CPU). ``materials``: the
    rooms' (:mod:`usf_graph.scenes.materials`; ``"random"``, the protocol's). ``gray``:
    every model reads only its views' luma (:func:`make_model`): a mono camera's protocol,
    its tests gray as well."""
    check_channel_scale(channel_scale)  # these before any rendering
    check_materials(materials)
    check_share(fov_share)
    if not (math.isfinite(balance) and balance >= 0):
        raise ValueError(f"balance is the class weights' power (0: none, 1: full "
                         f"median-frequency balancing), got {balance}")
    check_extra_rooms(seed, up_extra)
    dev = resolve_device(device)
    check_models(models, level)
    rank, _ = setup_distributed()
    seed_everything(seed)
    out, t0 = Path(out), time.time()
    sets = protocol_sets(root, size, level, num_train, num_test, seed, progress=progress,
                         materials=materials)
    results = {"samples": {"train": num_train, "test": num_test}, "size": size, "level": level,
               "epochs": epochs, "up_epochs": up_epochs, "balance": balance, "upright": upright,
               "up_extra": up_extra, "up_caps": up_caps, "up_sign": up_sign,
               "fov_epochs": fov_epochs, "fov_share": fov_share, "channel_scale": channel_scale,
               "materials": materials, "gray": gray}
    preds, shared = {}, {}
    trains_estimate = up_epochs and any(MODELS[n] is not PlanarUNet for n in models)  # else no extras
    extra = up_views(root, up_extra, f"icosahedral:{level}", progress, materials) \
        if trains_estimate else None
    up_kw = dict(caps=up_caps, extra=extra, sign_weight=up_sign)
    for name in models:
        seed_everything(seed)
        net = make_model(name, level, upright, channel_scale, gray).to(dev)
        t = time.time()
        train_model(net, sets["train"], out, name, epochs, batch_size, lr, seed, progress,
                    balance, up_epochs, shared, up_kw=up_kw, fov_epochs=fov_epochs,
                    fov_share=fov_share, resume=resume)
        if rank != 0:
            continue
        results.setdefault("train_seconds", {})[name] = round(time.time() - t, 1)
        results[name], preds[name] = evaluate_protocol(net, sets, progress=progress, name=name)
        save_checkpoint(out / f"{name}.pt", net, {"model": name, "size": size, **net.config},
                        results[name],
                        extra={"data": {"dataset": "rooms", "seed": seed, "materials": materials}})
    if rank != 0:
        return {}
    from ..viz import plot_segmentation

    return write_results(out, results, t0, "seg_results.png",
                         lambda p: plot_segmentation(sets, preds, p), resumed=resume)


def format_table(results: dict, metric: str = "mIoU") -> str:
    """The protocol table in Markdown: ``metric`` (in points) per model and test."""
    tests = [k for k in PROTOCOL if any(k in results.get(m, {}) for m in MODELS)]
    rows = ["| model | " + " | ".join(f"({k}) {PROTOCOL_NAMES[k]}" for k in tests) + " |",
            "|---" * (len(tests) + 1) + "|"]
    for name in MODELS:
        if name in results:
            rows.append(f"| {name} | " + " | ".join(
                f"{100 * results[name][k][metric]:.1f}" if k in results[name] else "-"
                for k in tests) + " |")
    return "\n".join(rows)
