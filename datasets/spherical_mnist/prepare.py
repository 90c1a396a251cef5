"""Download the full MNIST (IDX files, MD5-checked) and build Spherical MNIST splits.

    .venv/bin/python datasets/spherical_mnist/prepare.py --root data/mnist
    .venv/bin/python datasets/spherical_mnist/prepare.py --root data/mnist --train-rotate none so3

By default it builds what `usf-graph train mnist --root data/mnist --source idx` reads (NR
train, NR and SO(3) test, on the demo's icosahedral:5 grid): the full 60,000 / 10,000 digits.
Without network, put the four `*-ubyte.gz` files under --root by hand and pass
--skip-download.
"""

from __future__ import annotations

import argparse

from usf_graph.datasets import SphericalMNIST, download_mnist
from usf_graph.datasets.mnist import MNIST_MIRRORS


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default="data/mnist")
    ap.add_argument("--mirror", action="append", help="base URL to try first (repeatable)")
    ap.add_argument("--skip-download", action="store_true")
    ap.add_argument("--grid", default="icosahedral:5", help="the demo's input grid by default")
    modes = ["none", "so3", "chunk500"]
    ap.add_argument("--train-rotate", nargs="+", default=["none"], choices=modes,
                    help="add so3 for the R/R protocol")
    ap.add_argument("--test-rotate", nargs="+", default=["none", "so3"], choices=modes)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    if not a.skip_download:
        for p in download_mnist(a.root, tuple(a.mirror or ()) + MNIST_MIRRORS):
            print(f"ok  {p}")
    sets = {}
    for split, rotations in (("train", a.train_rotate), ("test", a.test_rotate)):
        for rot in rotations:
            ds = SphericalMNIST(a.root, split, grid=a.grid, rotate=rot, seed=a.seed, source="idx")
            sets[(split, rot)] = ds
            print(f"{split:5s} {rot:8s} {len(ds):6d} samples x {ds.x.shape[1]} points -> "
                  f"{ds.processed_paths[0]}")
    return sets


if __name__ == "__main__":
    main()
