"""Time one training step (forward, backward, Adam) of the Spherical MNIST classifier next to
its planar baseline, on CPU or a GPU.

    python benchmarks/train_step.py [--device cuda] [--batch 64] [--reps 10] [--form auto|wide|blockwise]

The spherical model is the demo's (``usf-graph train mnist`` defaults: input level 5, first
conv at level 4, down to level 2, jet and gradient pairs); the planar CNN is the demo's
baseline on 64x32 equirectangular images. Random inputs: the cost does not depend on them.
"""

from __future__ import annotations

import argparse

import torch
from timing import add_step_options, start_step, step_time

from usf_graph.models import PlanarCNN, SphericalClassifier
from usf_graph.train import defaults
from usf_graph.train.mnist import PLANAR_IMAGE
from usf_graph.train.mnist import run as mnist_run


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_step_options(p, batch=64, reps=10)
    a = p.parse_args()
    dev = start_step(a)
    d = defaults(mnist_run)
    sph = SphericalClassifier(level=d["level"], input_level=d["input_level"],
                              min_level=d["min_level"], pairs=d["pairs"],
                              pair_stages=d["pair_stages"]).to(dev)
    planar = PlanarCNN().to(dev)
    B = a.batch
    y = torch.randint(0, 10, (B,), device=dev)
    xs = torch.randn(B, sph.num_points, 1, device=dev)
    W, H = PLANAR_IMAGE
    xp = torch.randn(B, 1, H, W, device=dev)
    ce = torch.nn.functional.cross_entropy
    ts = step_time(sph, xs, y, ce, a.reps, dev)
    tp = step_time(planar, xp, y, ce, a.reps, dev)
    where = torch.cuda.get_device_name(dev) if dev.type == "cuda" else f"CPU, {a.threads} threads"
    print(f"{where}, batch {B}, best of {a.reps} steps, sparse kernel: {a.form}")
    print("| model | points | parameters | step (ms) | samples/s |")
    print("|---|---|---|---|---|")
    for name, m, n, t in (("SphericalClassifier", sph, sph.num_points, ts),
                          (f"PlanarCNN ({W}x{H})", planar, W * H, tp)):
        params = sum(q.numel() for q in m.parameters())
        print(f"| {name} | {n} | {params} | {1e3 * t:.1f} | {B / t:.0f} |")
    print(f"\nspherical / planar step time: {ts / tp:.1f}x")


if __name__ == "__main__":
    main()
