"""How much of the spherical U-Net's gap on the rooms protocol is the missing "up" cue?

Trains the spherical U-Net of ``usf-graph train seg`` three ways on the same upright
panoramas (200 rooms, icosahedral:5, 16 epochs, seed 0) and scores new rooms (test (a)):

* ``plain``: RGB only (the protocol's model before its up estimate);
* ``gravity``: ``SphericalUNet(gravity=True)``, the protocol's model, which estimates up
  equivariantly (:class:`~usf_graph.models.UpNet`) and reads each point's height along it
  as a fourth input channel;
* ``true_height``: RGB plus each point's true height ``p . z`` as a fourth channel. This is
  an upper bound, not a usable model: a rotated camera does not know its height.

    .venv/bin/python examples/seg_height_cue.py [--epochs 16] [--variants plain gravity true_height] [--tests a d]

Prints the area-weighted mIoU on the sphere (and the up error of the gravity variant).
About 5 minutes per variant on 2 cores, after the rooms are rendered (``data/rooms``).
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from torch import nn

from usf_graph.geometry import geodesic_distance
from usf_graph.models import SphericalUNet
from usf_graph.train.engine import fit
from usf_graph.train.seg import protocol_sets, segmentation_step
from usf_graph.train.seg_metrics import confusion_matrix, scores


def with_true_height(x: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
    """``[B, N, 3]`` RGB -> ``[B, N, 4]`` with the grid's z (upright views: the height)."""
    return torch.cat([x, pos[None, :, 2:].to(x.dtype).expand(len(x), -1, 1)], -1)


class WithTrueHeight(nn.Module):
    """A 4-channel model that reads RGB ``[B, N, 3]`` and is given the true height."""

    def __init__(self, net: nn.Module, pos: torch.Tensor):
        super().__init__()
        self.net, self.pos = net, pos

    def forward(self, x, mask=None, return_gravity=False):
        return self.net(with_true_height(x, self.pos), mask, return_gravity=return_gravity)


def sphere_miou(logits: torch.Tensor, test) -> float:
    """Area-weighted mIoU on the sphere of per-point ``logits [S, N, 13]``."""
    conf = confusion_matrix(logits.argmax(-1).numpy(), test.y.numpy(), 13,
                            weight=test.grid.area.numpy()[None])
    return scores(conf)["mIoU"]


@torch.no_grad()
def evaluate(net, test, name: str) -> tuple[dict, str]:
    """Scores on the test views, and for the gravity variant its up error and the score
    of the same network given the true up."""
    x, mask = test.x.float(), test.mask[0]
    mask = None if mask.all() else mask
    out = [net(x[i:i + 8], mask, return_gravity=True) for i in range(0, len(x), 8)]
    res = {"sphere_mIoU": sphere_miou(torch.cat([o[0] for o in out]), test)}
    line = f"{name}: sphere mIoU {100 * res['sphere_mIoU']:.1f}"
    if name == "gravity":
        up = torch.cat([o[1]["up"] for o in out])
        err = torch.rad2deg(geodesic_distance(up, torch.tensor([0.0, 0, 1]).expand_as(up)))
        res["up_err_median_deg"] = float(np.median(err.numpy()))
        res["up_err_mean_deg"] = float(err.mean())
        res["up_err_over_60deg"] = int((err > 60).sum())
        # the same network reading the true up instead of its estimate
        z = torch.tensor([[0.0, 0.0, 1.0]])
        true = torch.cat([net(x[i:i + 8], mask, up=z.expand(len(x[i:i + 8]), 3))
                          for i in range(0, len(x), 8)])
        res["sphere_mIoU_true_up"] = sphere_miou(true, test)
        line += (f", up error median {res['up_err_median_deg']:.1f} deg, mean "
                 f"{res['up_err_mean_deg']:.1f} deg, {res['up_err_over_60deg']} views over "
                 f"60 deg; with the true up: {100 * res['sphere_mIoU_true_up']:.1f}")
    return res, line


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--root", default="data/rooms")
    p.add_argument("--epochs", type=int, default=16)
    p.add_argument("--variants", nargs="+", default=["plain", "gravity", "true_height"],
                   choices=["plain", "gravity", "true_height"])
    p.add_argument("--size", type=int, default=96, help="panorama height")
    p.add_argument("--level", type=int, default=5)
    p.add_argument("--num-train", type=int, default=200)
    p.add_argument("--num-test", type=int, default=50)
    p.add_argument("--tests", nargs="+", default=["a"], choices=["a", "c", "d"],
                   help="upright protocol tests to score (c, d: other lenses, on what they see)")
    p.add_argument("--no-progress", action="store_true")
    a = p.parse_args(argv)
    sets = protocol_sets(a.root, a.size, a.level, a.num_train, a.num_test, tests=a.tests,
                         progress=not a.no_progress)
    train, pos = sets["train"], sets["train"].grid.pos

    results = {}
    for name in a.variants:
        net = SphericalUNet(13, in_channels=4 if name == "true_height" else 3, level=a.level,
                            gravity=name == "gravity")
        net = WithTrueHeight(net, pos) if name == "true_height" else net
        fit(net, train, None, epochs=a.epochs, batch_size=8, lr=3e-3, seed=0, name=name,
            step=segmentation_step, progress=not a.no_progress)
        for k in a.tests:
            res, line = evaluate(net.eval(), sets[k], name)
            results[name] = res if len(a.tests) == 1 else {**results.get(name, {}), k: res}
            print(f"({k}) {line}", flush=True)
    return results


if __name__ == "__main__":
    main()
