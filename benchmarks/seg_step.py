"""Time one training step (forward, backward, Adam) of the spherical U-Net next to the planar
U-Net at the same number of pixels and the same channels, on CPU or a GPU.

    python benchmarks/seg_step.py [--device cuda] [--batch 8] [--level 5] [--reps 5]
                                  [--model spherical_unet|spherical_deeplab]
                                  [--channel-scale 1.0]
                                  [--form auto|wide|blockwise]

Spherical: :class:`SphericalUNet` as ``usf-graph train seg`` builds and trains it (jet,
gradient pairs, up estimate) on ``icosahedral:level`` (N points): its up estimate is
trained beforehand and frozen, so the step reads the known up and never runs it. The up
estimate's own step (:func:`~usf_graph.train.gravity.up_step`, run ``up_epochs`` times per
view before) is timed on its own line. ``--model spherical_deeplab`` times the protocol's
DeepLab instead (its oriented kernels included), against the same planar U-Net. ``--channel-scale``: both models' channels times this, as
``usf-graph train seg --channel-scale`` builds them. Planar:
:class:`PlanarUNet` with the spherical U-Net's channels on an equirectangular image of H x
2H pixels, H the multiple of 8 nearest to sqrt(N / 2). Both with 13-class cross-entropy on random inputs and labels (the cost does not
depend on them), in the static-graph form with one field of view for the batch.
"""

from __future__ import annotations

import argparse
import math

import torch
from timing import add_step_options, start_step, step_time

from usf_graph.models import PlanarUNet, SphericalUNet
from usf_graph.train import defaults, scaled_channels
from usf_graph.train.seg import make_model, segmentation_loss


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_step_options(p, batch=8, reps=5)
    p.add_argument("--level", type=int, default=5)
    p.add_argument("--model", default="spherical_unet", choices=["spherical_unet", "spherical_deeplab"],
                   help="the spherical model (the 2x target is the U-Net's)")
    p.add_argument("--channel-scale", type=float, default=1.0,
                   help="both models' channels times this (as train seg's option)")
    a = p.parse_args()
    dev = start_step(a)
    sph = make_model(a.model, a.level, channel_scale=a.channel_scale).to(dev)
    unet = {**defaults(SphericalUNet), **scaled_channels(SphericalUNet, a.channel_scale)}
    planar = PlanarUNet(channels=unet["channels"]).to(dev)  # not a 2nd model
    N, B = sph.num_points, a.batch
    H = max(8, 8 * round(math.sqrt(N / 2) / 8))
    xs, ys = torch.rand(B, N, 3, device=dev), torch.randint(0, 13, (B, N), device=dev)
    xp, yp = torch.rand(B, 3, H, 2 * H, device=dev), torch.randint(0, 13, (B, H, 2 * H), device=dev)
    g = torch.tensor([[0.0, 0.0, 1.0]], device=dev).expand(B, 3)
    tu = step_time(sph.gravity, xs, g, lambda out, g: sph.gravity.head.loss(out, g), a.reps, dev,
                   warmup=2)
    sph.gravity.requires_grad_(False)
    ts = step_time(GivenUp(sph, g), xs, ys, segmentation_loss, a.reps, dev, warmup=2)
    tp = step_time(planar, xp, yp, segmentation_loss, a.reps, dev, warmup=2)
    where = torch.cuda.get_device_name(dev) if dev.type == "cuda" else f"CPU, {a.threads} threads"
    print(f"{where}, batch {B}, best of {a.reps} steps, channels {sph.config['channels']}, "
          f"sparse kernel: {a.form}")
    print("| model | points | parameters | step (ms) | samples/s |")
    print("|---|---|---|---|---|")
    for name, m, n, t in ((f"{type(sph).__name__} (icosahedral:{a.level})", sph, N, ts),
                          (f"PlanarUNet ({2 * H}x{H})", planar, 2 * H * H, tp)):
        params = sum(q.numel() for q in m.parameters())
        print(f"| {name} | {n} | {params} | {1e3 * t:.1f} | {B / t:.0f} |")
    print(f"\nspherical / planar step time: {ts / tp:.2f}x")
    print(f"up estimate alone (UpNet + GravityHead.loss): {1e3 * tu:.1f} ms")


class GivenUp(torch.nn.Module):
    """The segmenter as a training step calls it: reading the known up."""

    def __init__(self, net, up):
        super().__init__()
        self.net, self.up = net, up

    def forward(self, x):
        return self.net(x, up=self.up)


if __name__ == "__main__":
    main()
