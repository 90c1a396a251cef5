"""The timer the benchmarks share: best of several runs, synchronized on a GPU."""

from __future__ import annotations

import math
import time

import torch


def best_time(fn, reps: int, device: torch.device | str = "cpu", warmup: int = 1) -> float:
    """Seconds of the fastest of ``reps`` calls of ``fn`` after ``warmup`` calls; on CUDA each
    run ends with a synchronize, so queued kernels are counted."""
    dev = torch.device(device)

    def sync():
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    for _ in range(warmup):
        fn()
    sync()
    best = math.inf
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        sync()
        best = min(best, time.perf_counter() - t)
    return best


def step_time(model, x, y, loss_fn, reps: int, device, warmup: int = 3) -> float:
    """:func:`best_time` of one training step: forward, ``loss_fn(model(x), y)``, backward
    and an Adam update (warm-up: lazy structures, the allocator, cuDNN)."""
    opt = torch.optim.Adam(model.parameters(), 1e-3)

    def step():
        opt.zero_grad(set_to_none=True)
        loss_fn(model(x), y).backward()
        opt.step()

    return best_time(step, reps, device, warmup=warmup)


def add_step_options(parser, batch: int, reps: int) -> None:
    """The training-step benchmarks' ``--device``, ``--batch``, ``--reps``, ``--threads`` and
    ``--form`` (see :func:`start_step`)."""
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--batch", type=int, default=batch)
    parser.add_argument("--reps", type=int, default=reps)
    parser.add_argument("--threads", type=int, default=2, help="CPU threads")
    add_form_option(parser)


def start_step(args) -> torch.device:
    """Sets the sparse kernel's form and the CPU threads of :func:`add_step_options`'s
    arguments and seeds torch with 0; returns their device."""
    apply_form(args.form)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    return torch.device(args.device)


FORMS = {"auto": None, "wide": True, "blockwise": False}


def add_form_option(parser) -> None:
    """``--form``: the sparse kernel's form (``usf_graph.nn.aggregate.WIDE``)."""
    parser.add_argument("--form", default="auto", choices=list(FORMS),
                        help="the sparse kernel's form: auto takes one product per call on a "
                             "GPU and one per (sample, basis) block on the CPU")


def apply_form(form: str) -> None:
    """Sets the sparse kernel's form for what follows (``auto``, ``wide``, ``blockwise``)."""
    from usf_graph.nn import aggregate

    aggregate.WIDE = FORMS[form]


def in_form(form: str, f):
    """``f`` run with the sparse kernel in ``form``, the default form restored after."""
    def run(*args):
        apply_form(form)
        try:
            return f(*args)
        finally:
            apply_form("auto")
    return run
