"""Spherical MNIST end to end: train without rotations, test under SO(3) rotations."""

from __future__ import annotations

import time
from pathlib import Path

import torch
from torch.utils.data import TensorDataset

from ..cameras import Equirectangular
from ..datasets import SphericalMNIST
from ..frontend import SphericalFrontend
from ..models import PlanarCNN, SphericalClassifier
from .devices import resolve_device, setup_distributed
from .engine import (
    defaults,
    evaluate,
    fit,
    load_checkpoint,
    save_checkpoint,
    seed_everything,
    write_results,
)

#: The planar baseline's equirectangular images, width x height.
PLANAR_IMAGE = (64, 32)


def equirect_images(x: torch.Tensor, grid) -> torch.Tensor:
    """Spherical samples ``[S, N, 1]`` on ``grid`` -> the planar baseline's equirectangular
    images ``[S, 1, 32, 64]``."""
    fe = SphericalFrontend(Equirectangular(*PLANAR_IMAGE), grid)
    img = torch.stack([fe.to_image(x[i]) for i in range(len(x))])  # [S, H, W, 1]
    return img.permute(0, 3, 1, 2).contiguous()


def classifier_kind(blob: dict) -> str | None:
    """``"spherical"`` or ``"planar"`` for a checkpoint of ``usf-graph train mnist`` (its
    recorded model, or, saved before session 62, its config's keys); None for any other."""
    data, cfg = blob.get("data") or {}, blob.get("config") or {}
    if data.get("dataset") == "mnist":
        return data["model"]
    if {"level", "readout"} <= set(cfg):
        return "spherical"
    return "planar" if set(cfg) == {"in_channels", "num_classes", "channels"} else None


def load_classifier(path) -> tuple[torch.nn.Module, dict]:
    """The trained model of a ``usf-graph train mnist`` checkpoint, and what it was trained
    on: ``{"model": "spherical" | "planar", "grid": spec, "seed": int | None, "provenance":
    dict | None}`` (the planar model reads :func:`equirect_images` of that grid's samples).
    Checkpoints saved before session 62 record neither the seed nor a planar model's grid
    (:func:`run`'s default input level then, with a note)."""
    blob = load_checkpoint(path)
    kind = classifier_kind(blob)
    if kind is None:
        raise ValueError(f"{path} is not a checkpoint of 'usf-graph train mnist'; score those "
                         "of 'train seg|det' with 'usf-graph eval seg|det'")
    cfg, data = blob["config"], blob.get("data") or {}
    model = SphericalClassifier.from_config(cfg) if kind == "spherical" else PlanarCNN(**cfg)
    model.load_state_dict(blob["state_dict"])
    grid = data.get("grid")
    if grid is None:
        level = model.input_level if kind == "spherical" else defaults(run)["input_level"]
        grid = f"icosahedral:{level}"
        if kind == "planar":
            print(f"note: {path} does not record the grid its images came from (saved before "
                  f"session 62); reading them from {grid}, the run's default")
    return model, {"model": kind, "grid": grid, "seed": data.get("seed"),
                   "provenance": blob.get("provenance")}


def score(path, root="data/mnist", rotate: str = "so3", seed: int | None = None,
          source: str = "auto", device: str | None = None, progress: bool = True) -> dict:
    """The loss and accuracy of a ``usf-graph train mnist`` checkpoint on the test digits
    under ``rotate`` (``none``, ``so3``, ``chunk500``), their rotations drawn from ``seed``
    (default: the run's own, so that ``so3`` gives its NR/R number), and what
    :func:`load_classifier` says it is."""
    dev = resolve_device(device)  # before the digits are processed: a bad device loses nothing
    model, info = load_classifier(path)
    seed = seed if seed is not None else (info["seed"] or 0)
    ds = SphericalMNIST(root, "test", grid=info["grid"], rotate=rotate, seed=seed, source=source,
                        progress=progress)
    x = ds.x if info["model"] == "spherical" else equirect_images(ds.x, ds.grid)
    model.to(dev)
    m = evaluate(model, TensorDataset(x, ds.y), progress=progress)
    return {**m, **info, "seed": seed, "rotate": rotate}


def run(root="data/mnist", out="runs/mnist", level: int = 4, epochs: int = 12,
        batch_size: int = 32, seed: int = 0, source: str = "auto", planar: bool = True,
        progress: bool = True, input_level: int | None = 5, min_level: int | None = 2,
        pairs: int = 16, pair_stages: int = 2, resume: bool = False,
        device: str | None = None) -> dict:
    """Train the spherical classifier (and the planar baseline) on unrotated digits and
    report NR/NR and NR/R accuracy. The digits are lifted to ``input_level`` (the jet is
    taken there), the convolutions start on
    ``level`` and pool down to ``min_level``; ``pairs``/``pair_stages``: the
    :class:`~usf_graph.nn.GradientPairs` layers. Writes results.json, checkpoints and a figure.
    ``resume``: continue an interrupted run under ``out`` (:func:`~usf_graph.train.engine.fit`).
    ``device``: where the models train and are scored
    (:func:`~usf_graph.train.devices.resolve_device`; default the CPU).

    Under ``torchrun`` every process trains its share; rank 0 alone evaluates and writes
    (the other ranks return ``{}``)."""
    dev = resolve_device(device)
    rank, _ = setup_distributed()
    seed_everything(seed)
    out = Path(out)
    t0 = time.time()
    model = SphericalClassifier(level=level, input_level=input_level, min_level=min_level,
                                pairs=pairs, pair_stages=pair_stages)
    grid = f"icosahedral:{model.input_level}"
    kw = dict(grid=grid, source=source, progress=progress)
    train = SphericalMNIST(root, "train", rotate="none", **kw)
    test_nr = SphericalMNIST(root, "test", rotate="none", **kw)
    test_r = SphericalMNIST(root, "test", rotate="so3", seed=seed, **kw)
    sets = {k: TensorDataset(d.x, d.y) for k, d in
            (("train", train), ("NR", test_nr), ("R", test_r))}
    results = {"samples": {"train": len(train), "test": len(test_nr)}, "grid": grid}

    def train_and_score(name, net, data):
        """Fit on unrotated digits; rank 0 scores NR and R and writes ``<name>.pt`` (with
        what :func:`load_classifier` reads back)."""
        fit(net, data["train"], data["NR"], epochs=epochs, batch_size=batch_size, seed=seed,
            log_dir=out / name, config=net.config, progress=progress, name=name, resume=resume,
            device=dev)
        if rank == 0:
            results[name] = {k: evaluate(net, data[k], desc=f"{name} {k}",
                                         progress=progress)["acc"] for k in ("NR", "R")}
            save_checkpoint(out / f"{name}.pt", net, net.config, results[name], extra={"data": {
                "dataset": "mnist", "model": name, "grid": grid, "seed": seed}})
        net.cpu()  # the figure runs it on the CPU's test digits

    train_and_score("spherical", model, sets)
    if planar:
        pl = {k: TensorDataset(equirect_images(d.tensors[0], train.grid), d.tensors[1])
              for k, d in sets.items()}
        train_and_score("planar", PlanarCNN(), pl)
    if rank != 0:
        return {}
    from ..viz import plot_mnist_results

    return write_results(out, results, t0, "mnist_results.png",
                         lambda p: plot_mnist_results(results, model, test_r, p), resumed=resume)


def format_table(results: dict) -> str:
    rows = ["| model | NR/NR | NR/R | drop |", "|---|---|---|---|"]
    for name in ("spherical", "planar"):
        if name in results:
            r = results[name]
            rows.append(f"| {name} | {100 * r['NR']:.2f} | {100 * r['R']:.2f} | "
                        f"{100 * (r['NR'] - r['R']):.2f} |")
    return "\n".join(rows)
