"""Time one training step (forward, loss, backward, Adam) of the detection protocol's
spherical detector next to its planar detector, on CPU or a GPU.

    python benchmarks/det_step.py [--device cuda] [--batch 8] [--size 128] [--reps 5]
                                  [--channel-scale 1.0] [--boxes 4]
                                  [--form auto|wide|blockwise]

Spherical: :func:`~usf_graph.train.det.make_detector` as ``usf-graph train det`` builds it
(up estimate, ``UprightConv`` stages) on icosahedral:5; its up estimate is trained
beforehand and frozen, so the step reads the known up. Planar: :class:`PlanarDetector` on
the protocol's ``2 size x size`` panoramas. Both with their own losses (focal heatmaps and
box regression) on random inputs and ``--boxes`` random boxes per view (the cost hardly
depends on them), ``--channel-scale`` as ``usf-graph train det --channel-scale``.
"""

from __future__ import annotations

import argparse
import math

import torch
from seg_step import GivenUp
from timing import add_step_options, start_step, step_time

from usf_graph.models import PlanarDetector
from usf_graph.scenes import DETECTION_CLASSES
from usf_graph.train import scaled_channels
from usf_graph.train.det import make_detector


def random_boxes(batch: int, per_view: int, gen: torch.Generator):
    """``per_view`` boxes on each view, ``(boxes [K, 5], classes [K], image [K])``:
    centres up to 40 degrees from the horizon, 10 to 50 degrees wide and tall, rolled up to
    45 degrees either way."""
    k = batch * per_view
    u = torch.rand(k, 5, generator=gen)
    boxes = torch.stack([(2 * u[:, 0] - 1) * math.pi, (2 * u[:, 1] - 1) * math.radians(40),
                         math.radians(10) + u[:, 2] * math.radians(40),
                         math.radians(10) + u[:, 3] * math.radians(40),
                         (2 * u[:, 4] - 1) * math.pi / 4], -1)
    classes = torch.randint(0, len(DETECTION_CLASSES), (k,), generator=gen)
    return boxes, classes, torch.arange(batch).repeat_interleave(per_view)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_step_options(p, batch=8, reps=5)
    p.add_argument("--size", type=int, default=128, help="the planar panoramas' height")
    p.add_argument("--boxes", type=int, default=4, help="random boxes per view")
    p.add_argument("--channel-scale", type=float, default=1.0,
                   help="both models' channels times this (as train det's option)")
    a = p.parse_args()
    dev = start_step(a)
    sph = make_detector(channel_scale=a.channel_scale).to(dev)
    sph.gravity.requires_grad_(False)
    planar = PlanarDetector(height=a.size, width=2 * a.size,
                            **scaled_channels(PlanarDetector, a.channel_scale)).to(dev)
    B, N = a.batch, sph.num_points
    target = tuple(t.to(dev) for t in random_boxes(B, a.boxes, torch.Generator().manual_seed(0)))
    xs = torch.rand(B, N, 3, device=dev)
    xp = torch.rand(B, 3, a.size, 2 * a.size, device=dev)
    up = torch.tensor([[0.0, 0.0, 1.0]], device=dev).expand(B, 3)

    def loss(model):
        return lambda out, t: model.loss(out, *t)[0]

    ts = step_time(GivenUp(sph, up), xs, target, loss(sph), a.reps, dev, warmup=2)
    tp = step_time(planar, xp, target, loss(planar), a.reps, dev, warmup=2)
    where = torch.cuda.get_device_name(dev) if dev.type == "cuda" else f"CPU, {a.threads} threads"
    print(f"{where}, batch {B}, {a.boxes} boxes per view, best of {a.reps} steps, channel scale "
          f"{a.channel_scale:g}, sparse kernel: {a.form}")
    print("| model | points | trained parameters | step (ms) | samples/s |")
    print("|---|---|---|---|---|")
    for name, m, n, t in (("SphericalDetector (icosahedral:5)", sph, N, ts),
                          (f"PlanarDetector ({2 * a.size}x{a.size})", planar, 2 * a.size ** 2, tp)):
        params = sum(q.numel() for q in m.parameters() if q.requires_grad)
        print(f"| {name} | {n} | {params} | {1e3 * t:.1f} | {B / t:.0f} |")
    print(f"\nspherical / planar step time: {ts / tp:.2f}x")


if __name__ == "__main__":
    main()
