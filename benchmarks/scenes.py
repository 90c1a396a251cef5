"""Rendering speed of the procedural rooms: a full view with every label (RGB, labels,
instances, depth, boxes) against Embree alone finding the first hits of the same pixels.

    python benchmarks/scenes.py [--rooms 5] [--threads 2]

Each view is a new viewpoint, so its boxes are computed from scratch (the dense spherical
cast and the refinement strips). The issue's budget: 512x256 in at most 0.25 s, 2048x1024 in
at most 2 s, on 2 cores. Times are medians over the rooms.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from usf_graph import cameras, scenes
from usf_graph.scenes.lenses import protocol_cameras
from usf_graph.scenes.render import world_boxes


def _time(fn, *args, **kwargs):
    t = time.perf_counter()
    fn(*args, **kwargs)
    return time.perf_counter() - t


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--rooms", type=int, default=5)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--sizes", default="256,512,1024")
    a = p.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", str(a.threads))
    cams = {f"equirectangular {2 * s}x{s}": cameras.Equirectangular(2 * s, s)
            for s in (int(v) for v in a.sizes.split(","))}
    lenses = protocol_cameras(512)
    cams["fisheye190 512x512"], cams["pinhole90 512x512"] = lenses["fisheye190"], lenses["pinhole90"]
    rooms = [scenes.make_room(0, i) for i in range(a.rooms)]
    scenes.render(rooms[0], cameras.Equirectangular(64, 32))  # textures, first Embree call
    t_room = np.median([_time(scenes.make_room, 1, i) for i in range(a.rooms)])
    print(f"building a room: {1000 * t_room:.0f} ms (median of {a.rooms})\n")
    print("| camera | full view (ms) | no boxes (ms) | boxes alone (ms) | Embree first hits (ms) | full / Embree | budget |")
    print("|---|---|---|---|---|---|---|")
    for name, cam in cams.items():
        lnm, valid = cam.lens_normal_map()
        scenes.render(rooms[0], cam, view=99)  # camera rays cached, as in a dataset
        full, plain, boxes, embree = [], [], [], []
        for k, room in enumerate(rooms):
            room._boxes.clear()
            full.append(_time(scenes.render, room, cam, view=k))
            plain.append(_time(scenes.render, room, cam, view=k, boxes=False))
            p0, R = room.viewpoint(k)
            room._boxes.clear()
            boxes.append(_time(world_boxes, room, p0))
            embree.append(_time(room.cast, p0, lnm[valid] @ R.T))
        f, e = np.median(full), np.median(embree)
        budget = {512 * 256: "0.25 s", 2048 * 1024: "2 s"}.get(cam.width * cam.height, "")
        print(f"| {name} | {1000 * f:.0f} | {1000 * np.median(plain):.0f} | "
              f"{1000 * np.median(boxes):.0f} | {1000 * e:.0f} | {f / e:.1f} | {budget} |")


if __name__ == "__main__":
    main()
