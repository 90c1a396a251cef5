"""Where a run computes: the device (CPU or a GPU) and the processes of a ``torchrun``
group (DistributedDataParallel over gloo)."""

from __future__ import annotations

import itertools
import os

import torch
import torch.distributed as dist
from torch import nn


def resolve_device(device: str | torch.device | None = None) -> torch.device:
    """The device a run trains and predicts on: ``None`` or ``"cpu"``: the CPU; ``"cuda"``:
    the GPU (under ``torchrun``, the process's own, ``cuda:LOCAL_RANK``); ``"cuda:N"``;
    ``"auto"``: a GPU when torch sees one, else the CPU. A device this machine does not
    have is a ValueError that says so, not a failure deep inside the first step."""
    if device is None:
        return torch.device("cpu")
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as e:
        raise ValueError(f"unknown device {device!r}: give cpu, cuda, cuda:N or auto") from e
    if dev.type == "cpu":
        return dev
    if dev.type != "cuda":
        raise ValueError(f"device {device!r}: usf-graph trains on cpu or cuda (its sparse "
                         "products need one of them)")
    if not torch.cuda.is_available():
        raise ValueError(f"device {device!r}: this torch sees no CUDA GPU "
                         "(torch.cuda.is_available() is False); use --device cpu, or install a "
                         "CUDA build of torch on a machine with a GPU")
    if dev.index is None:
        dev = torch.device("cuda", int(os.environ.get("LOCAL_RANK", 0)))
    if dev.index >= torch.cuda.device_count():
        raise ValueError(f"device {dev}: this machine has {torch.cuda.device_count()} GPU(s)")
    return dev


def model_device(model: nn.Module) -> torch.device:
    """Where ``model``'s parameters (else buffers) are; the CPU for a model with neither."""
    t = next(itertools.chain(model.parameters(), model.buffers()), None)
    return torch.device("cpu") if t is None else t.device


def is_planar(model: nn.Module) -> bool:
    """Whether a model (or its DDP wrapper) takes images ``[B, C, H, W]``."""
    return getattr(getattr(model, "module", model), "input_dims", 3) == 4


def to_device(batch, device: torch.device):
    """``batch`` with every tensor on ``device``: a tensor, a PyG ``Data`` or ``Batch`` (moved
    in place, as its ``to`` does), or tuples, lists and dicts of them (nested); anything
    else (None, numbers) as it is."""
    from torch_geometric.data.data import BaseData

    if torch.is_tensor(batch) or isinstance(batch, BaseData):
        return batch.to(device)
    if isinstance(batch, (tuple, list)):
        return type(batch)(to_device(b, device) for b in batch)
    if isinstance(batch, dict):
        return {k: to_device(v, device) for k, v in batch.items()}
    return batch


def is_distributed() -> bool:
    """Whether this process is in a ``torchrun`` process group."""
    return dist.is_available() and dist.is_initialized()


def setup_distributed() -> tuple[int, int]:
    """Join the process group when launched by ``torchrun``: gloo, which reduces gradients
    on the CPU and on GPUs alike (NCCL, which the group took whenever CUDA was present,
    takes only CUDA tensors, so DistributedDataParallel failed there on the CPU; the group
    is joined before a run knows its device)."""
    if "WORLD_SIZE" not in os.environ or int(os.environ["WORLD_SIZE"]) <= 1:
        return 0, 1
    if not is_distributed():
        dist.init_process_group("gloo")
    return dist.get_rank(), dist.get_world_size()


def teardown_distributed() -> None:
    """Leave the process group together: every rank waits for the others, then the group
    is destroyed. A rank that simply exits while another still works kills gloo's threads
    (``terminate called without an active exception``)."""
    if is_distributed():
        dist.barrier()
        dist.destroy_process_group()
