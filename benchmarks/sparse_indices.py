"""int32 against int64 indices in the sparse CSR matrices of the layers, in one run.

torch's CPU sparse products (MKL) take int32 row pointers and columns and convert int64
ones on every product. Since session 59 the layers keep int32 indices
(:func:`usf_graph.sparse.index_dtype`); setting ``usf_graph.sparse.INT32_LIMIT`` to 0 before
a model is built and first called gives it int64 ones, as before. Timed, interleaved rep
by rep so that the machine's drift falls on both alike: one sparse product of a level-5
convolution's size, the protocols' spherical DeepLab and detector on a fisheye frame
(the network with the up given, as ``predict_frame.py`` times it), and a training step
of the DeepLab (forward, backward; the transposed matrices work there).

    python benchmarks/sparse_indices.py [--reps 20] [--threads 2] [--batch 2]
                                        [--channel-scale 1.0] [--size 512] [--tasks seg det]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from predict_frame import LENSES, models

from usf_graph import sparse
from usf_graph.scenes.lenses import protocol_cameras
from usf_graph.train import apply


def interleaved(fns: dict, reps: int) -> dict:
    """``{name: [seconds per rep]}``, the functions called in turn, rep by rep."""
    times = {k: [] for k in fns}
    for _ in range(reps):
        for k, fn in fns.items():
            t = time.perf_counter()
            fn()
            times[k].append(time.perf_counter() - t)
    return times


def with_indices(limit: int, build):
    """``build()`` with ``sparse.INT32_LIMIT`` at ``limit`` (0: int64 indices)."""
    old, sparse.INT32_LIMIT = sparse.INT32_LIMIT, limit
    try:
        return build()
    finally:
        sparse.INT32_LIMIT = old


def product_case(n: int = 10242, degree: int = 8, channels: int = 64):
    """One CSR product ``A @ x`` of a level-5 convolution's size, per index dtype."""
    gen = torch.Generator().manual_seed(0)
    rows = torch.arange(n).repeat_interleave(degree)
    cols = (rows + torch.randint(-40, 41, (len(rows),), generator=gen)).clamp(0, n - 1)
    key = torch.unique(rows * n + cols)
    rows, cols = key // n, key % n
    crow = sparse.row_pointers(torch.bincount(rows, minlength=n))
    vals, x = torch.rand(len(cols), generator=gen), torch.rand(n, channels, generator=gen)
    out = {}
    for name, limit in (("int32", 2 ** 31), ("int64", 0)):
        idx = with_indices(limit, lambda: sparse.csr_indices(crow, cols, n))
        with sparse.quiet_sparse():
            A = torch.sparse_csr_tensor(*idx, vals, (n, n))
        out[name] = lambda A=A: A @ x
    return out


def network_cases(task: str, batch: int, scale: float, size: int) -> tuple[dict, dict]:
    """The network (channels times ``scale``) on a ``size x size`` fisheye frame, and
    (seg) a training step, per index dtype."""
    cam = protocol_cameras(size)[LENSES["fisheye"]]
    image = (np.random.default_rng(0).random((cam.height, cam.width, 3)) * 255).astype(np.uint8)
    forward, step = {}, {}
    for name, limit in (("int32", 2 ** 31), ("int64", 0)):
        torch.manual_seed(0)

        def build():
            net = models(task, scale)[0].eval()
            _, x, mask = apply.lift_for(net, image, cam)
            up = torch.tensor([[0.0, 0.0, 1.0]])
            with torch.no_grad():
                net(x, mask, up=up)  # builds the lazily made structures
            if task == "seg":  # and the transposes, in a training step
                xb, ub = x.expand(batch, -1, -1).contiguous(), up.expand(batch, 3)
                net.train()
                net(xb, mask, up=ub).square().mean().backward()
                net.eval()
            return net, x, mask, up

        net, x, mask, up = with_indices(limit, build)

        @torch.no_grad()
        def fwd(net=net, x=x, mask=mask, up=up):
            net(x, mask, up=up)

        forward[name] = fwd
        if task == "seg":
            xb, ub = x.expand(batch, -1, -1).contiguous(), up.expand(batch, 3)

            def train_step(net=net, xb=xb, mask=mask, ub=ub):
                net.train()
                net.zero_grad()
                net(xb, mask, up=ub).square().mean().backward()
                net.eval()

            step[name] = train_step
    return forward, step


def row(label: str, times: dict) -> str:
    a, b = np.array(times["int32"]) * 1e3, np.array(times["int64"]) * 1e3
    return (f"| {label} | {np.median(a):.2f} ({a.min():.2f}) | {np.median(b):.2f} ({b.min():.2f}) "
            f"| {np.median(b) / np.median(a):.2f}x |")


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--reps", type=int, default=20)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--batch", type=int, default=2, help="the training step's batch")
    p.add_argument("--channel-scale", type=float, default=1.0, help="the models' channels times this")
    p.add_argument("--size", type=int, default=512, help="the fisheye image's height and width")
    p.add_argument("--tasks", nargs="+", default=["seg", "det"], choices=["seg", "det"])
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    print(f"{a.threads} CPU threads, {a.reps} reps interleaved; ms, median (best)\n")
    print("| | int32 indices | int64 indices | int64 / int32 |")
    print("|---|---|---|---|")
    print(row("one sparse product, 10,242 x 10,242, 64 channels",
              interleaved(product_case(), 10 * a.reps)))
    for task, label in (("seg", "DeepLab"), ("det", "detector")):
        if task not in a.tasks:
            continue
        forward, step = network_cases(task, a.batch, a.channel_scale, a.size)
        print(row(f"{label} network, fisheye frame, up given", interleaved(forward, a.reps)))
        if step:
            print(row(f"{label} training step, batch {a.batch}",
                      interleaved(step, max(2, a.reps // 4))))


if __name__ == "__main__":
    main()
