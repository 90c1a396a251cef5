"""Panoramas into YouTube's equi-angular cube map (EAC) and back, frame by frame: a
:class:`~usf_graph.frontend.Reimager` (the geometry built once, one ``cv2.remap`` a frame)
against FFmpeg's ``v360`` filter (``e`` <-> ``eac``, bilinear), the tool 360 video is
converted with, through PyAV, side by side in one run.

    python benchmarks/eac.py [--sizes 1024 2048 4096] [--reps 3] [--threads 2]

A uint8 RGB panorama ``size x size / 2`` goes into an EAC frame ``3/4 size x 1/2 size``
(faces about ``size / 4``, as dense as the panorama at the faces' centres), and that frame
back into the panorama. FFmpeg's graph is configured once per job and fed one frame at a
time (its side includes PyAV's copies between numpy and FFmpeg's frames, which a Python
user pays too); it builds its maps on the first frame, whose time is printed apart, as is
the Reimager's build. The last column compares the results (mean absolute difference in
grey levels on the pixels with rays: the EAC's faces, the whole panorama).
"""

from __future__ import annotations

import argparse
import time
from fractions import Fraction

import cv2
import numpy as np
import torch
from conv import timeit as best_of  # noqa: E402  (benchmarks/ is the script's folder)

from usf_graph.cameras import EquiAngularCubemap, Equirectangular
from usf_graph.frontend import Reimager
from usf_graph.viz import labelled_panorama


class V360:
    """FFmpeg's v360 filter as a callable on RGB uint8 frames of one size."""

    def __init__(self, width: int, height: int, args: str, threads: int):
        import av

        self.av, self.pts = av, 0
        self.graph = av.filter.Graph()
        self.graph.threads = threads
        self.src = self.graph.add_buffer(width=width, height=height, format="rgb24",
                                         time_base=Fraction(1, 25))
        v360 = self.graph.add("v360", f"{args}:interp=linear")
        self.sink = self.graph.add("buffersink")
        self.src.link_to(v360)
        v360.link_to(self.sink)
        self.graph.configure()

    def __call__(self, image: np.ndarray) -> np.ndarray:
        frame = self.av.VideoFrame.from_ndarray(image, format="rgb24")
        frame.pts, self.pts = self.pts, self.pts + 1
        self.src.push(frame)
        return self.sink.pull().to_ndarray(format="rgb24")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[1024, 2048, 4096])
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--threads", type=int, default=2)
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    cv2.setNumThreads(a.threads)
    print("| job | first call: ours (s) | first frame: FFmpeg (s) | ours (ms/frame) | "
          "FFmpeg (ms/frame) | ratio | difference |")
    print("|---|---|---|---|---|---|---|")
    for size in a.sizes:
        pano_cam = Equirectangular(size, size // 2)
        eac_cam = EquiAngularCubemap(3 * size // 4, size // 2)
        pano = (255 * labelled_panorama(size, size // 2)).round().astype(np.uint8)
        eac = Reimager(pano_cam, eac_cam)(pano)
        jobs = (("panorama -> EAC", pano_cam, eac_cam, pano, "input=e:output=eac"),
                ("EAC -> panorama", eac_cam, pano_cam, eac, "input=eac:output=e"))
        for name, src, dst, image, args in jobs:
            t = time.perf_counter()
            r = Reimager(src, dst)
            ours_out = r(image)
            first = time.perf_counter() - t
            t = time.perf_counter()
            theirs = V360(src.width, src.height, f"{args}:w={dst.width}:h={dst.height}", a.threads)
            theirs_out = theirs(image)  # its maps built on the first frame
            their_first = time.perf_counter() - t
            ours = best_of(lambda: r(image), a.reps)  # noqa: B023
            other = best_of(lambda: theirs(image), a.reps)  # noqa: B023
            seen = dst.pixels_with_rays()
            diff = np.abs(ours_out.astype(np.float64) - theirs_out)[seen].mean()
            print(f"| {name} {size}x{size // 2} | {first:.2f} | {their_first:.2f} | "
                  f"{1e3 * ours:.1f} | {1e3 * other:.1f} | {other / ours:.1f}x | {diff:.1f} |",
                  flush=True)


if __name__ == "__main__":
    main()
