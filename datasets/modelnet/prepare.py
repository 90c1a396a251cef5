"""Download ModelNet10/40 (the official zip), unzip it and sample both splits.

    .venv/bin/python datasets/modelnet/prepare.py --root data/modelnet --name 40 --num-points 1024

Without network, unzip the archive under --root by hand (root/ModelNet40/<class>/...) and
run the same command: nothing is downloaded when the folder exists.
"""

from __future__ import annotations

import argparse

from usf_graph.datasets import ModelNet


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default="data/modelnet")
    ap.add_argument("--name", default="40", choices=["10", "40"])
    ap.add_argument("--num-points", type=int, default=1024)
    ap.add_argument("--url", default=None, help="zip to download instead of the official one")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    sets = {}
    for split in ("train", "test"):
        ds = ModelNet(a.root, a.name, split, a.num_points, a.seed, url=a.url)
        sets[split] = ds
        print(f"{split:5s} {len(ds):5d} clouds x {a.num_points} points, {len(ds.classes)} classes "
              f"-> {ds.processed_paths[0]}")
    return sets


if __name__ == "__main__":
    main()
