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

from fractions import Fraction

import numpy as np
from cubemap import compare, header, parse  # noqa: E402  (benchmarks/ is the script's folder)

from usf_graph.cameras import EquiAngularCubemap, Equirectangular
from usf_graph.frontend import Reimager
from usf_graph.viz import labelled_panorama


class V360:
    """FFmpeg's v360 filter as a callable on RGB uint8 frames of one size; its graph is
    configured (its maps built) on the first call, which the first-frame column times."""

    def __init__(self, width: int, height: int, args: str, threads: int):
        self.size, self.args, self.threads, self.pts, self.graph = (width, height), args, threads, 0, None

    def _configure(self) -> None:
        import av

        self.graph = av.filter.Graph()
        self.graph.threads = self.threads
        self.src = self.graph.add_buffer(width=self.size[0], height=self.size[1], format="rgb24",
                                         time_base=Fraction(1, 25))
        v360 = self.graph.add("v360", f"{self.args}:interp=linear")
        self.sink = self.graph.add("buffersink")
        self.src.link_to(v360)
        v360.link_to(self.sink)
        self.graph.configure()

    def __call__(self, image: np.ndarray) -> np.ndarray:
        import av

        if self.graph is None:
            self._configure()
        frame = av.VideoFrame.from_ndarray(image, format="rgb24")
        frame.pts, self.pts = self.pts, self.pts + 1
        self.src.push(frame)
        return self.sink.pull().to_ndarray(format="rgb24")


def main(argv=None) -> None:
    a = parse(argv, __doc__)
    header("FFmpeg", "first frame")
    for size in a.sizes:
        pano_cam = Equirectangular(size, size // 2)
        eac_cam = EquiAngularCubemap(3 * size // 4, size // 2)
        pano = (255 * labelled_panorama(size, size // 2)).round().astype(np.uint8)
        eac = Reimager(pano_cam, eac_cam)(pano)
        compare([(name, src, dst, image,
                  V360(src.width, src.height, f"{args}:w={dst.width}:h={dst.height}", a.threads))
                 for name, src, dst, image, args in (
                     ("panorama -> EAC", pano_cam, eac_cam, pano, "input=e:output=eac"),
                     ("EAC -> panorama", eac_cam, pano_cam, eac, "input=eac:output=e"))],
                size, a.reps, seen_only=True)


if __name__ == "__main__":
    main()
