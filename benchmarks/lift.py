"""Lifting throughput: SphericalFrontend (cold and warm) vs a bare cv2.remap of the same
number of points, for a 1024x2048 panorama and a 1280x960 fisheye onto icosahedral level 7.

    python benchmarks/lift.py [--level 7] [--threads 2] [--reps 20]

cold = geometry built from scratch (lens projection of every grid point, tables, graph,
and the lens's per-pixel rays, which cameras.kept would otherwise keep from the row before);
warm = geometry cached, only the signal moves. The floor is cv2.remap with the same maps
already in memory: the least any lifting can do.
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np
import torch
from conv import timeit as best_of  # noqa: E402  (benchmarks/ is the script's folder)

from usf_graph import SphericalFrontend, cameras, grids
from usf_graph.cameras.kept import forget_rays
from usf_graph.frontend import GeometryCache


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--level", type=int, default=7)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--reps", type=int, default=20)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    cv2.setNumThreads(a.threads)
    g = grids.icosahedral(a.level)
    g.area  # noqa: B018  (grid construction is not part of lifting)
    rng = np.random.default_rng(0)
    cams = {
        "panorama 2048x1024": cameras.Equirectangular(2048, 1024),
        "fisheye 1280x960 (KB, 190 deg)": cameras.KannalaBrandt(
            400.0, 400.0, 639.5, 479.5, 1280, 960, k=(0.01, -0.002, 0.0005, -0.0001), fov_deg=190),
    }
    print(f"grid icosahedral:{a.level} ({len(g)} points), {a.threads} threads, best of {a.reps}")
    print("| camera | image | cold build (ms) | warm lift (ms) | cv2.remap floor (ms) "
          "| cold / warm | warm / floor |")
    print("|---|---|---|---|---|---|---|")
    for name, cam in cams.items():
        for dtype, C in ((np.uint8, 3), (np.float32, 1)):
            img = (rng.random((cam.height, cam.width, C)) * 255).astype(dtype)
            forget_rays()
            t = time.perf_counter()
            fe = SphericalFrontend(cam, g, cache=GeometryCache(None))
            fe.lift(img)
            cold = time.perf_counter() - t
            warm = best_of(lambda fe=fe, img=img: fe.lift(img), a.reps)
            mx, my = fe._remap().maps
            border = cv2.BORDER_WRAP if cam.wraps_u else cv2.BORDER_CONSTANT
            floor = best_of(lambda img=img, mx=mx, my=my, b=border:
                            cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=b),
                            a.reps)
            print(f"| {name} | {np.dtype(dtype).name} x{C} | {1e3 * cold:.0f} | {1e3 * warm:.2f} "
                  f"| {1e3 * floor:.2f} | {cold / warm:.0f}x | {warm / floor:.2f}x |", flush=True)


if __name__ == "__main__":
    main()
