"""A protocol split rendered by one process and by several (``USF_GRAPH_RENDER_WORKERS``):
the segmentation protocol's panoramas (192x96 onto icosahedral:5, labels, no boxes) and
the detection protocol's (256x128 onto icosahedral:5, with boxes). Each configuration
renders into a fresh folder, after a warm-up (the lift table, the textures); the stored
splits are checked to be equal.

    python benchmarks/render_split.py [--views 64] [--workers 1,2]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import torch

from usf_graph import cameras
from usf_graph.datasets import RoomsDetection, RoomsSegmentation
from usf_graph.datasets.rooms import WORKERS_ENV

SPLITS = {"segmentation 192x96": (RoomsSegmentation, cameras.Equirectangular(192, 96)),
          "detection 256x128": (RoomsDetection, cameras.Equirectangular(256, 128))}


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--views", type=int, default=64)
    p.add_argument("--workers", default="1,2", help="comma-separated process counts")
    a = p.parse_args()
    counts = [int(w) for w in a.workers.split(",")]
    print(f"{a.views} views per split, {os.cpu_count()} cores")
    print("\n| split | " + " | ".join(f"{w} process{'es' * (w > 1)} (s)" for w in counts)
          + " | speed-up |")
    print("|---|" + "---|" * (len(counts) + 1))
    for name, (cls, cam) in SPLITS.items():
        with tempfile.TemporaryDirectory() as root:  # builds the lift table, loads textures
            os.environ[WORKERS_ENV] = "1"
            cls(root, camera=cam, num_scenes=1, progress=False)
        times, stored = [], []
        for w in counts:
            os.environ[WORKERS_ENV] = str(w)
            with tempfile.TemporaryDirectory() as root:
                t = time.perf_counter()
                ds = cls(root, camera=cam, num_scenes=a.views, progress=False)
                times.append(time.perf_counter() - t)
                stored.append((ds.x, ds.y, ds.image))
        same = all(torch.equal(u, v) for s in stored[1:] for u, v in zip(stored[0], s))
        if not same:
            raise SystemExit(f"{name}: the splits differ between process counts")
        print(f"| {name} | " + " | ".join(f"{t:.1f}" for t in times)
              + f" | {times[0] / min(times[1:] or times):.2f}x |")


if __name__ == "__main__":
    main()
