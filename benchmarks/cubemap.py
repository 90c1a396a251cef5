"""Panoramas into cube maps and back, frame by frame: a :class:`~usf_graph.frontend.Reimager`
(the geometry built once, one ``cv2.remap`` a frame) against py360convert's ``e2c`` and
``c2e``, the field's library for it, side by side in one run.

    python benchmarks/cubemap.py [--sizes 1024 2048 4096] [--reps 3] [--threads 2]

A uint8 RGB equirectangular panorama ``size x size / 2`` goes into a ``horizon`` cube map of
faces ``size / 4`` square (the same pixel density at the faces' edges), and that cube map
back into the panorama. py360convert works in float and caches its coordinate tables
between calls of one size, so both sides time the per-frame cost after a first call; the
Reimager's build is printed apart. The last columns compare the two results (mean absolute
difference in grey levels: py360convert puts its faces' pixel centres on the faces' edges
and its panorama's on -180 and 180 degrees, half a pixel from ours).
"""

from __future__ import annotations

import argparse
import time
from functools import partial

import cv2
import numpy as np
import torch
from conv import timeit as best_of  # noqa: E402  (benchmarks/ is the script's folder)

from usf_graph.cameras import Cubemap, Equirectangular
from usf_graph.frontend import Reimager
from usf_graph.viz import labelled_panorama


def parse(argv, doc: str):
    """The re-imaging benchmarks' options, with torch's and OpenCV's threads set."""
    p = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[1024, 2048, 4096])
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--threads", type=int, default=2)
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    cv2.setNumThreads(a.threads)
    return a


def header(other: str, first: str = "first call") -> None:
    print(f"| job | first call: ours (s) | {first}: {other} (s) | ours (ms/frame) | "
          f"{other} (ms/frame) | ratio | difference |")
    print("|---|---|---|---|---|---|---|")


def compare(jobs, size: int, reps: int, seen_only: bool = False) -> None:
    """One table row per job ``(name, source camera, target camera, image, theirs)``: a
    Reimager's first call and theirs, then each one's best of ``reps`` frames, and the
    mean absolute difference of the results (``seen_only``: on the target's pixels with
    rays)."""
    for name, src, dst, image, theirs in jobs:
        t = time.perf_counter()
        r = Reimager(src, dst)
        ours_out = r(image)
        first = time.perf_counter() - t
        t = time.perf_counter()
        theirs_out = theirs(image)  # its tables built (and cached) on the first call
        their_first = time.perf_counter() - t
        ours = best_of(lambda: r(image), reps)  # noqa: B023
        other = best_of(lambda: theirs(image), reps)  # noqa: B023
        d = np.abs(ours_out.astype(np.float64) - np.asarray(theirs_out, np.float64))
        diff = (d[dst.pixels_with_rays()] if seen_only else d).mean()
        print(f"| {name} {size}x{size // 2} | {first:.2f} | {their_first:.2f} | "
              f"{1e3 * ours:.1f} | {1e3 * other:.1f} | {other / ours:.1f}x | {diff:.1f} |",
              flush=True)


def main(argv=None) -> None:
    a = parse(argv, __doc__)
    import py360convert

    header("py360convert")
    for size in a.sizes:
        pano_cam, cube_cam = Equirectangular(size, size // 2), Cubemap(size // 4)
        pano = (255 * labelled_panorama(size, size // 2)).round().astype(np.uint8)
        cube = Reimager(pano_cam, cube_cam)(pano)
        compare((("panorama -> cube map", pano_cam, cube_cam, pano,
                  partial(py360convert.e2c, face_w=size // 4, mode="bilinear", cube_format="horizon")),
                 ("cube map -> panorama", cube_cam, pano_cam, cube,
                  partial(py360convert.c2e, h=size // 2, w=size, mode="bilinear", cube_format="horizon"))),
                size, a.reps)


if __name__ == "__main__":
    main()
