"""The training engine shared by every task: fit / evaluate, logs, checkpoints, DDP."""

from __future__ import annotations

import csv
import json
import math
import os
import random
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch import nn
from torch.utils.data import DataLoader, Dataset, DistributedSampler
from tqdm.auto import tqdm

from ..fileio import atomic_torch_save


def seed_everything(seed: int, deterministic: bool = True) -> None:
    """Seed python, numpy and torch; make torch kernels deterministic where it can."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    if deterministic:
        torch.use_deterministic_algorithms(True, warn_only=True)


def is_distributed() -> bool:
    return dist.is_available() and dist.is_initialized()


def setup_distributed() -> tuple[int, int]:
    """Join the process group when launched by ``torchrun`` (gloo on CPU, nccl on GPU)."""
    if "WORLD_SIZE" not in os.environ or int(os.environ["WORLD_SIZE"]) <= 1:
        return 0, 1
    if not is_distributed():
        dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
    return dist.get_rank(), dist.get_world_size()


def teardown_distributed() -> None:
    """Leave the process group together: every rank waits for the others, then the group
    is destroyed. A rank that simply exits while another still works kills gloo's threads
    (``terminate called without an active exception``)."""
    if is_distributed():
        dist.barrier()
        dist.destroy_process_group()


def save_checkpoint(path, model: nn.Module, config: dict, metrics: dict,
                    optimizer=None, scheduler=None, epoch: int = 0) -> None:
    """Atomically write state_dict, config, metrics (and optimizer state for resuming)."""
    model = model.module if hasattr(model, "module") else model
    blob = {"state_dict": model.state_dict(), "config": config, "metrics": metrics,
            "epoch": epoch}
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
        raise ValueError(f"{path} is not a readable usf-graph checkpoint ({e})") from e
    if not isinstance(blob, dict) or "state_dict" not in blob:
        raise ValueError(f"{path} is not a usf-graph checkpoint (no state_dict)")
    if model is not None:
        model.load_state_dict(blob["state_dict"])
    return blob


def _batches(dataset: Dataset, batch_size: int, shuffle: bool, seed: int, epoch: int):
    sampler = None
    if is_distributed():
        sampler = DistributedSampler(dataset, shuffle=shuffle, seed=seed, drop_last=False)
        sampler.set_epoch(epoch)
        batch_size = batch_size // dist.get_world_size()
    g = torch.Generator().manual_seed(seed + epoch)
    return DataLoader(dataset, batch_size=batch_size, shuffle=shuffle and sampler is None,
                      sampler=sampler, generator=g)


@torch.no_grad()
def evaluate(model: nn.Module, dataset: Dataset, batch_size: int = 256,
             desc: str = "eval", progress: bool = True) -> dict:
    """Loss and accuracy of a classifier over a dataset of (x, y) pairs."""
    model.eval()
    loss, correct, n = 0.0, 0, 0
    loader = DataLoader(dataset, batch_size=batch_size)
    for x, y in tqdm(loader, desc=desc, leave=False, disable=not progress):
        out = model(x)
        loss += nn.functional.cross_entropy(out, y, reduction="sum").item()
        correct += (out.argmax(-1) == y).sum().item()
        n += len(y)
    return {"loss": loss / max(n, 1), "acc": correct / max(n, 1)}


def fit(model: nn.Module, train: Dataset, val: Dataset | None = None, epochs: int = 10,
        batch_size: int = 32, lr: float = 3e-3, weight_decay: float = 1e-4, seed: int = 0,
        log_dir=None, config: dict | None = None, resume: bool = False, progress: bool = True,
        name: str = "model", on_epoch: Callable[[int, dict], None] | None = None) -> dict:
    """Train a classifier with AdamW and a cosine schedule.

    Logs ``metrics.csv`` / ``metrics.json`` (and TensorBoard when installed) under
    ``log_dir`` and writes ``last.pt`` each epoch; ``resume=True`` continues from it.
    Under ``torchrun`` the model is wrapped in DistributedDataParallel and each process
    takes its share of every global batch of ``batch_size``.
    """
    rank, world = setup_distributed()
    seed_everything(seed)
    if world > 1:
        model = nn.parallel.DistributedDataParallel(model)
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=weight_decay)
    steps = epochs * math.ceil(len(train) / batch_size)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: 0.5 * (1 + math.cos(math.pi * min(s, steps) / max(steps, 1))))
    log_dir = Path(log_dir) if log_dir is not None else None
    start, history = 0, []
    if resume and log_dir is not None and (log_dir / "last.pt").exists():
        blob = load_checkpoint(log_dir / "last.pt", model.module if world > 1 else model)
        opt.load_state_dict(blob["optimizer"])
        sched.load_state_dict(blob["scheduler"])
        start, history = blob["epoch"], blob["metrics"].get("history", [])
    writer = _tensorboard(log_dir) if rank == 0 else None
    for epoch in range(start, epochs):
        model.train()
        bar = tqdm(_batches(train, batch_size, True, seed, epoch), leave=False,
                   desc=f"{name} epoch {epoch + 1}/{epochs}", disable=not progress or rank != 0)
        tot, correct, n = 0.0, 0, 0
        for x, y in bar:
            out = model(x)
            loss = nn.functional.cross_entropy(out, y)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            tot += loss.item() * len(y)
            correct += (out.argmax(-1) == y).sum().item()
            n += len(y)
            bar.set_postfix(loss=f"{tot / n:.3f}", acc=f"{correct / n:.3f}")
        row = {"epoch": epoch + 1, "train_loss": tot / n, "train_acc": correct / n,
               "lr": sched.get_last_lr()[0]}
        if val is not None and rank == 0:
            v = evaluate(model.module if world > 1 else model, val, progress=False)
            row.update(val_loss=v["loss"], val_acc=v["acc"])
        history.append(row)
        if rank == 0:
            if progress:
                tqdm.write(f"{name} epoch {epoch + 1}/{epochs}: " +
                           ", ".join(f"{k}={v:.4g}" for k, v in row.items() if k != "epoch"))
            if log_dir is not None:
                _log(log_dir, history, writer)
                save_checkpoint(log_dir / "last.pt", model, config or {}, {"history": history},
                                opt, sched, epoch + 1)
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
    with open(log_dir / "metrics.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(history)
    (log_dir / "metrics.json").write_text(json.dumps(history, indent=1))
    if writer is not None:
        for k, v in history[-1].items():
            if k != "epoch":
                writer.add_scalar(k, v, history[-1]["epoch"])
