"""The training engine shared by every task: fit / evaluate, logs, checkpoints (devices and
DDP: :mod:`.devices`)."""

from __future__ import annotations

import contextlib
import csv
import inspect
import json
import math
import numbers
import random
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch import nn
from torch.utils.data import DataLoader, Dataset, DistributedSampler
from tqdm.auto import tqdm

from ..fileio import atomic_torch_save, atomic_write, load_refusal
from ..nn.norm import MaskedBatchNorm
from .devices import is_distributed, model_device, resolve_device, setup_distributed, to_device

Step = Callable[[nn.Module, Any], tuple[torch.Tensor, dict, int]]


def defaults(fn: Callable) -> dict:
    """``fn``'s keyword defaults, ``{name: default}``: the one source of a protocol's
    settings (its ``run``) for the command line and the examples that reuse them."""
    return {k: v.default for k, v in inspect.signature(fn).parameters.items()
            if v.default is not inspect.Parameter.empty}


# the constructor arguments that count channels, in the protocols' models
CHANNEL_ARGS = ("channels", "aspp_channels", "low_channels")


def check_channel_scale(scale: float) -> float:
    """``scale`` if it is a usable width multiplier, in (0, 4]; else a ValueError (a run
    checks it before it renders anything)."""
    if not (math.isfinite(scale) and 0 < scale <= 4):
        raise ValueError(f"the channel scale must be in (0, 4], got {scale}")
    return scale


def scaled_channels(cls: Callable, scale: float) -> dict:
    """Keyword arguments that build ``cls`` with every default channel count in
    :data:`CHANNEL_ARGS` times ``scale`` (rounded, at least 8): a width multiplier, ``{}``
    for ``scale`` 1. At 0.5 a planar U-Net's step costs about 0.3x, a spherical model's
    0.6x: the jets and the sparse products' index work do not shrink
    (``benchmarks/README.md``)."""
    if check_channel_scale(scale) == 1:
        return {}
    d = defaults(cls)
    return {k: [max(8, round(c * scale)) for c in d[k]] if isinstance(d[k], (tuple, list))
            else max(8, round(d[k] * scale)) for k in CHANNEL_ARGS if k in d}


def seed_everything(seed: int, deterministic: bool = True) -> None:
    """Seed python, numpy and torch; make torch kernels deterministic where it can."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    if deterministic:
        torch.use_deterministic_algorithms(True, warn_only=True)


def save_checkpoint(path, model: nn.Module, config: dict, metrics: dict,
                    optimizer=None, scheduler=None, epoch: int = 0, extra: dict | None = None) -> None:
    """Atomically write state_dict, config, metrics, where it came from
    (:func:`~usf_graph.train.provenance.provenance`), and optimizer state for resuming
    (``extra``: more entries, e.g. :func:`fit`'s random states)."""
    from .provenance import provenance

    model = model.module if hasattr(model, "module") else model
    blob = {"state_dict": model.state_dict(), "config": config, "metrics": metrics,
            "epoch": epoch, "provenance": provenance(), **(extra or {})}
    if optimizer is not None:
        blob["optimizer"] = optimizer.state_dict()
    if scheduler is not None:
        blob["scheduler"] = scheduler.state_dict()
    atomic_torch_save(blob, path)


def load_checkpoint(path, model: nn.Module | None = None) -> dict:
    """Load a checkpoint safely (``weights_only=True``) and optionally fill ``model``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001
        raise ValueError(f"{path} is not a readable usf-graph checkpoint: corrupt, truncated, or "
                         f"not written by usf-graph ({load_refusal(e)}). Train it again or copy it again; "
                         "do not load a file you do not trust with weights_only=False") from e
    if not isinstance(blob, dict) or "state_dict" not in blob:
        raise ValueError(f"{path} is not a usf-graph checkpoint (no state_dict)")
    if model is not None:
        model.load_state_dict(blob["state_dict"])
    return blob


def group_batches(groups, batch_size: int, seed: int = 0, epoch: int = 0,
                  shuffle: bool = True) -> list[list[int]]:
    """One epoch's batches of sample indices, each within one group: ``groups [S]`` gives
    every sample's group (e.g. its field of view: the samples of a batch must share one,
    :func:`field_groups`). Every sample comes once; with ``shuffle`` the samples and the
    batches' order are drawn from ``seed + epoch`` (the same on every process)."""
    groups = np.asarray(groups).reshape(-1)
    if not (isinstance(batch_size, numbers.Integral) and batch_size >= 1):
        raise ValueError(f"batch_size must be a whole number of at least 1, got {batch_size}")
    g = torch.Generator().manual_seed(seed + epoch)
    order = torch.randperm(len(groups), generator=g).tolist() if shuffle else range(len(groups))
    members: dict = {}
    for i in order:
        members.setdefault(groups[i].item(), []).append(i)
    batches = [m[j:j + batch_size] for m in members.values() for j in range(0, len(m), batch_size)]
    if shuffle:
        batches = [batches[i] for i in torch.randperm(len(batches), generator=g).tolist()]
    return batches


def field_groups(mask: torch.Tensor) -> np.ndarray:
    """``[S]`` group ids of samples by field of view (``mask [S, N]``): equal masks, one
    id; for :func:`fit`'s ``groups``, when a dataset's samples come from several cameras."""
    if mask.dim() != 2:
        raise ValueError(f"mask must be [S, N], got {tuple(mask.shape)}")
    return torch.unique(mask.bool(), dim=0, return_inverse=True)[1].numpy()


def _batches(dataset: Dataset, batch_size: int, shuffle: bool, seed: int, epoch: int,
             collate_fn=None, groups=None):
    if groups is not None:
        batches = group_batches(groups, batch_size, seed, epoch, shuffle)
        if is_distributed():  # each process its share of every batch, none empty
            rank, world = dist.get_rank(), dist.get_world_size()
            batches = [(b * math.ceil(world / len(b)))[rank::world] for b in batches]
        return _loader(dataset, 1, collate_fn, batch_sampler=batches)
    sampler = None
    if is_distributed():
        sampler = DistributedSampler(dataset, shuffle=shuffle, seed=seed, drop_last=False)
        sampler.set_epoch(epoch)
        batch_size = batch_size // dist.get_world_size()
    g = torch.Generator().manual_seed(seed + epoch)
    return _loader(dataset, batch_size, collate_fn, shuffle=shuffle and sampler is None,
                   sampler=sampler, generator=g)


def _loader(dataset, batch_size: int, collate_fn, **kw) -> DataLoader:
    """A DataLoader; PyG datasets and lists of ``Data`` (without a ``collate_fn`` of their
    own) get PyG's, whose batches are :class:`torch_geometric.data.Batch` objects."""
    from torch_geometric.data import Dataset as PyGDataset
    from torch_geometric.data.data import BaseData

    graphs = isinstance(dataset, PyGDataset) or (
        isinstance(dataset, (list, tuple)) and bool(dataset) and isinstance(dataset[0], BaseData))
    if collate_fn is None and graphs:
        from torch_geometric.loader import DataLoader as PyGLoader

        return PyGLoader(dataset, batch_size=batch_size, **kw)
    return DataLoader(dataset, batch_size=batch_size, collate_fn=collate_fn, **kw)


def classification_step(model: nn.Module, batch) -> tuple[torch.Tensor, dict, int]:
    """The default step: cross-entropy of a classifier on an ``(x, y)`` batch.

    A step takes ``(model, batch)`` and returns ``(loss, stats, n)``: the loss to minimize,
    batch means of anything worth logging (floats) and the number of samples."""
    x, y = batch
    out = model(x)
    loss = nn.functional.cross_entropy(out, y)
    return loss, {"acc": (out.argmax(-1) == y).double().mean().item()}, len(y)


class _Mean:
    """Sample-weighted running means of a step's loss and stats."""

    def __init__(self):
        self.sums, self.n = {}, 0

    def add(self, loss: torch.Tensor, stats: dict, n: int) -> None:
        for k, v in {"loss": loss.item(), **stats}.items():
            self.sums[k] = self.sums.get(k, 0.0) + v * n
        self.n += n

    def means(self) -> dict:
        return {k: v / max(self.n, 1) for k, v in self.sums.items()}


@torch.no_grad()
def evaluate(model: nn.Module, dataset: Dataset, batch_size: int = 256,
             desc: str = "eval", progress: bool = True, step: Step = classification_step,
             collate_fn=None) -> dict:
    """Mean loss and stats of ``step`` over a dataset (for the default step, the loss and
    accuracy of a classifier over ``(x, y)`` pairs), on the device the model is on."""
    model.eval()
    mean, dev = _Mean(), model_device(model)
    loader = _loader(dataset, batch_size, collate_fn)
    for batch in tqdm(loader, desc=desc, leave=False, disable=not progress):
        mean.add(*step(model, batch if dev.type == "cpu" else to_device(batch, dev)))
    return mean.means()


def freeze_norms(model: nn.Module) -> nn.Module:
    """Puts every batch normalization of ``model`` (torch's and
    :class:`~usf_graph.nn.MaskedBatchNorm`) in evaluation mode: it normalizes with its
    running statistics and leaves them unchanged, while its scale and shift still train.
    For fine-tuning on batches whose own statistics differ from what the model meets at
    test time: parts of the sphere, say, where every test view is normalized with the
    running statistics of whole ones."""
    for m in model.modules():
        if isinstance(m, (nn.modules.batchnorm._BatchNorm, MaskedBatchNorm)):
            m.eval()
    return model


def fit(model: nn.Module, train: Dataset, val: Dataset | None = None, epochs: int = 10,
        batch_size: int = 32, lr: float = 3e-3, weight_decay: float = 1e-4, seed: int = 0,
        log_dir=None, config: dict | None = None, resume: bool = False, progress: bool = True,
        name: str = "model", on_epoch: Callable[[int, dict], None] | None = None,
        step: Step = classification_step, collate_fn=None, frozen_norms: bool = False,
        device: str | torch.device | None = None, groups=None) -> dict:
    """Train a model with AdamW and a cosine schedule; ``step(model, batch) -> (loss,
    stats, n)`` says what a batch's loss is (default: :func:`classification_step`), and
    ``collate_fn`` how samples make a batch (the DataLoader's; PyG datasets are batched
    by PyG's loader into :class:`~torch_geometric.data.Batch` objects by default).

    Logs ``metrics.csv`` / ``metrics.json`` (and TensorBoard when installed) under
    ``log_dir`` and writes ``last.pt`` each epoch; ``resume=True`` continues from it, after
    its last finished epoch (a finished run just loads its weights). With the model, the
    optimizer and the schedule it restores torch's random state and the draws of a
    ``collate_fn`` that has a ``state_dict`` (e.g. the protocols' ``ThroughRandomFields``),
    so the run goes on as it would have without the interruption. A ``last.pt`` of another
    ``config`` or plan (epochs, batch size, learning rate, seed, training set size) is an
    error, not a silent mix.
    Under ``torchrun`` the model is wrapped in DistributedDataParallel and each process
    takes its share of every global batch of ``batch_size`` (a multiple of the number of
    processes, unless batches are drawn by ``groups``). ``frozen_norms``: batch
    normalizations keep their running statistics (:func:`freeze_norms`).

    ``groups [S]``: every batch is drawn from one group's samples
    (:func:`group_batches`), e.g. of one field of view (:func:`field_groups`) for a
    dataset of several cameras, whose batches must each share one.

    ``device`` (:func:`resolve_device`; ``None``: where the model is) moves the model there
    and each batch after the ``collate_fn``; the protocols' steps draw only from the CPU's
    generators (the known up's jitter, the fields of view), so a GPU run draws what a CPU
    run does and a resumed one goes on as on the CPU. Its numbers still differ from the
    CPU's in the last digits (other kernels).
    """
    if not all(isinstance(v, numbers.Integral) and v >= 1 for v in (epochs, batch_size)):
        raise ValueError(f"{name}: epochs and batch_size must be whole numbers of at least 1, "
                         f"got {epochs} and {batch_size}")
    if not (math.isfinite(lr) and lr > 0):
        raise ValueError(f"{name}: the learning rate must be a finite number above 0, got {lr}")
    if not len(train):
        raise ValueError(f"{name}: the training set is empty")
    if groups is not None and len(groups) != len(train):
        raise ValueError(f"{name}: groups has {len(groups)} entries for {len(train)} samples")
    rank, world = setup_distributed()
    if world > 1 and groups is None and batch_size % world:
        # a smaller global batch, and more steps than the schedule counts (its last at lr 0)
        raise ValueError(f"{name}: batch_size {batch_size} does not split evenly over {world} "
                         f"processes; give a multiple of {world}")
    seed_everything(seed)
    dev = model_device(model) if device is None else resolve_device(device)
    model.to(dev)
    if world > 1:
        model = nn.parallel.DistributedDataParallel(
            model, device_ids=None if dev.type == "cpu" else [dev.index])
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=weight_decay)
    steps = epochs * (math.ceil(len(train) / batch_size) if groups is None
                      else len(group_batches(groups, batch_size, shuffle=False)))
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: 0.5 * (1 + math.cos(math.pi * min(s, steps) / max(steps, 1))))
    log_dir = Path(log_dir) if log_dir is not None else None
    start, history = 0, []
    plan = {"epochs": epochs, "batch_size": batch_size, "lr": lr, "seed": seed, "samples": len(train)}
    stateful = collate_fn if hasattr(collate_fn, "state_dict") else None
    if resume and log_dir is not None and (log_dir / "last.pt").exists():
        blob = load_checkpoint(log_dir / "last.pt")
        for what, saved, now in (("config", blob["config"], config or {}),
                                 ("plan", blob.get("plan"), plan)):
            if saved != now:
                raise ValueError(f"{log_dir / 'last.pt'} was written with {what} {saved}, this "
                                 f"run has {now}: resume with the same options, or train "
                                 "into another folder")
        (model.module if world > 1 else model).load_state_dict(blob["state_dict"])
        opt.load_state_dict(blob["optimizer"])
        sched.load_state_dict(blob["scheduler"])
        start, history = blob["epoch"], blob["metrics"].get("history", [])
        torch.set_rng_state(blob["rng"])
        if stateful is not None:
            stateful.load_state_dict(blob["collate"])
    writer = _tensorboard(log_dir) if rank == 0 else None
    with writer or contextlib.nullcontext():  # closed, so TensorBoard has every epoch
        for epoch in range(start, epochs):
            model.train()
            if frozen_norms:
                freeze_norms(model)
            bar = tqdm(_batches(train, batch_size, True, seed, epoch, collate_fn, groups), leave=False,
                       desc=f"{name} epoch {epoch + 1}/{epochs}", disable=not progress or rank != 0)
            mean = _Mean()
            for i, batch in enumerate(bar):
                loss, stats, n = step(model, batch if dev.type == "cpu" else to_device(batch, dev))
                if not torch.isfinite(loss.detach()).all():
                    # one bad step makes every weight NaN; stop before a checkpoint keeps them
                    raise FloatingPointError(
                        f"{name}: the loss is {loss.detach().flatten()[0].item()} at epoch {epoch + 1}, "
                        f"batch {i + 1}: training diverged; lower the learning rate (lr={lr}) or "
                        f"check the inputs for NaN" + (f"; {log_dir / 'last.pt'} holds the last "
                                                       "finished epoch" if log_dir is not None else ""))
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                sched.step()
                mean.add(loss.detach(), stats, n)
                bar.set_postfix({k: f"{v:.3f}" for k, v in mean.means().items()})
            row = {"epoch": epoch + 1, **{f"train_{k}": v for k, v in mean.means().items()},
                   "lr": sched.get_last_lr()[0]}
            if val is not None and rank == 0:
                v = evaluate(model.module if world > 1 else model, val, progress=False, step=step,
                             collate_fn=collate_fn, batch_size=max(batch_size, 32))
                row.update({f"val_{k}": x for k, x in v.items()})
            history.append(row)
            if rank == 0:
                if progress:
                    tqdm.write(f"{name} epoch {epoch + 1}/{epochs}: " +
                               ", ".join(f"{k}={v:.4g}" for k, v in row.items() if k != "epoch"))
                if log_dir is not None:
                    _log(log_dir, history, writer)
                    state = {"plan": plan, "rng": torch.get_rng_state()}
                    if stateful is not None:
                        state["collate"] = stateful.state_dict()
                    save_checkpoint(log_dir / "last.pt", model, config or {}, {"history": history},
                                    opt, sched, epoch + 1, extra=state)
                if on_epoch is not None:
                    on_epoch(epoch, row)
    if world > 1:
        dist.barrier()  # rank 0 may still be evaluating or writing; leave fit together
    return {"history": history}


def _tensorboard(log_dir):
    if log_dir is None:
        return None
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(str(log_dir))


def _log(log_dir: Path, history: list[dict], writer) -> None:
    log_dir.mkdir(parents=True, exist_ok=True)
    keys = sorted({k for r in history for k in r}, key=lambda k: (k != "epoch", k))

    def table(f):
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(history)
    atomic_write(log_dir / "metrics.csv", table, mode="w")
    atomic_write(log_dir / "metrics.json", lambda f: f.write(json.dumps(history, indent=1)), mode="w")
    if writer is not None:
        for k, v in history[-1].items():
            if k != "epoch":
                writer.add_scalar(k, v, history[-1]["epoch"])


def write_results(out, results: dict, t0: float, figure: str | None = None,
                  plot: Callable[[Path], object] | None = None, resumed: bool = False) -> dict:
    """Finish a task's run: add its wall time (``seconds`` since ``t0``; with ``resumed``,
    recorded as ``"resumed"``, that time is only this invocation's, without the stages it
    loaded) and provenance, write ``results.json`` under ``out`` (atomically), then draw
    ``figure`` with ``plot(path)`` when given. A failed plot is reported and must not lose
    the results, which are already written."""
    import time

    from .provenance import provenance

    out = Path(out)
    results["seconds"] = round(time.time() - t0, 1)
    results["resumed"] = resumed
    results["provenance"] = provenance()
    text = json.dumps(results, indent=1)
    atomic_write(out / "results.json", lambda f: f.write(text), mode="w")
    if figure is None:
        return results
    try:
        plot(out / figure)
        results["figure"] = str(out / figure)
    except Exception as e:  # noqa: BLE001
        print(f"[usf-graph] could not draw the figure: {e}")
    return results
