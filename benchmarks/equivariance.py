"""Equivariance error on real grids, next to the interpolation error of the same rotation.

    python benchmarks/equivariance.py [--grids icosahedral:4,...] [--widths 128,256]

A smooth 3-channel signal and the same signal under a Haar rotation are lifted through an
equirectangular camera; a 2-layer SphericalConv network (random weights, float64) runs on
both, and its rotated output is compared (usf_graph.testing). Conv2d does the same on the
equirectangular image. ratio = network error / interpolation error.
"""

from __future__ import annotations

import argparse

import torch

from usf_graph import grids
from usf_graph.geometry import random_rotation
from usf_graph.testing import (
    equirect_equivariance_error,
    grid_equivariance_error,
    random_spherical_net,
    smooth_signal,
)

GRIDS = "icosahedral:4,icosahedral:5,healpix:16,healpix:32,fibonacci:2562,fibonacci:10242"


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--grids", default=GRIDS, help="comma-separated grid specs")
    p.add_argument("--widths", default="128,256", help="comma-separated panorama widths for Conv2d")
    a = p.parse_args()
    R = random_rotation(seed=7)
    print("| grid | points | kernel | interpolation error | network error | ratio |")
    print("|---|---|---|---|---|---|")
    for spec in a.grids.split(","):
        g = grids.from_spec(spec)
        for rs, K, basis in ((4.0, 3, "gaussian"), (2.0, 4, "hat")):
            e = grid_equivariance_error(random_spherical_net(g, rs, K, basis), g, smooth_signal, R)
            print(f"| {spec} | {len(g)} | {basis} K={K}, r={rs:g} spacings | "
                  f"{e['interpolation']:.2e} | {e['network']:.2e} | {e['ratio']:.1f} |", flush=True)
    for W in (int(w) for w in a.widths.split(",")):
        torch.manual_seed(0)
        conv = torch.nn.Sequential(torch.nn.Conv2d(3, 16, 3, padding=1), torch.nn.Tanh(),
                                   torch.nn.Conv2d(16, 8, 3, padding=1)).double()
        e = equirect_equivariance_error(conv, smooth_signal, R, W)
        print(f"| equirectangular {W}x{W // 2} | {W * W // 2} | Conv2d 3x3 | "
              f"{e['interpolation']:.2e} | {e['network']:.2e} | {e['ratio']:.1f} |", flush=True)


if __name__ == "__main__":
    main()
