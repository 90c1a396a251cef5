"""Up from straight lines on large panoramas: ``frontend.lines.lines_up`` against the first
version of its cube path, side by side in one run.

    python benchmarks/lines.py [--sizes 1024 2048 4096] [--threads 2] [--reps 2]

The panorama is a procedural room tilted by 17 degrees, rendered at 2048x1024 and resized
for the other widths. ``lines_up`` re-images it through six cube faces of at most
``MAX_FACE`` pixels a side, the source's valid pixels computed once and the image and its
coverage re-imaged together. The reference is the path as first written: faces at the
panorama's own pixel density, and two re-imagings a face (the image, then its coverage),
each of which unprojects every source pixel again. Both then search the same Manhattan
axes. Printed: seconds (best of ``reps``), the ratio, and each answer's error against the
room's true up.

    python benchmarks/lines.py --video 30 [--sizes 1024 2048]

A video instead: a room filmed while the camera turns 3 degrees a frame and sways (up
moving about a degree a frame, up to 12 degrees off level). ``UpTracker`` (the straight
views built once, the search near the last frame's up) against ``lines_up`` on every
frame; printed: seconds a frame (mean over the frames after the first), the ratio, and the
mean and worst error of each.
"""

from __future__ import annotations

import argparse
import math
import time

import cv2
import numpy as np
import torch

from usf_graph.cameras import Equirectangular
from usf_graph.frontend import lines as L
from usf_graph.frontend import render
from usf_graph.geometry import geodesic_distance, rotation_from_axis_angle
from usf_graph.scenes import make_room
from usf_graph.scenes import render as render_room


def reference_up(image, camera) -> np.ndarray:
    """The first version: uncapped faces, each re-imaged twice from the whole source."""
    gray, seen = L._gray(image), camera.lens_normal_map()[1]
    cap, L.MAX_FACE = L.MAX_FACE, 1 << 14
    try:
        faces = L._faces(camera)
    finally:
        L.MAX_FACE = cap
    found = [L._segment_normals(render(gray, camera, f), render(seen.astype(np.float32), camera, f) > 0.5,
                                f, None) for f in faces]
    axes = L.manhattan_axes(np.concatenate([n for n, _ in found]), np.concatenate([w for _, w in found]))
    p = L.image_up(camera)
    k = int(np.abs(axes @ p).argmax())
    return axes[k] * np.sign(axes[k] @ p)


def best(fn, reps: int, *args):
    """``fn(*args)``'s best time of ``reps`` (s), and its answer."""
    times, out = [], None
    for _ in range(reps):
        t = time.perf_counter()
        out = fn(*args)
        times.append(time.perf_counter() - t)
    return min(times), out


def video(sizes, frames: int) -> None:
    """The ``--video`` table."""
    scene = make_room(seed=3, index=3, materials="by_kind")
    pos, R0 = scene.viewpoint(0)
    print("| panorama | frames | UpTracker (s/frame) | lines_up (s/frame) | ratio | "
          "error: tracker mean / worst | lines_up mean / worst (deg) |")
    print("|---|---|---|---|---|---|---|")
    for w in sizes:
        cam = Equirectangular(w, w // 2)
        track, t_track, t_each, e_track, e_each = L.UpTracker(cam), [], [], [], []
        for k in range(frames):
            T = rotation_from_axis_angle(np.array([0.0, 0.0, 1.0]), math.radians(3 * k)) \
                @ rotation_from_axis_angle(np.array([math.cos(k / 7), math.sin(k / 7), 0.0]),
                                           math.radians(12 * math.sin(k / 5)))
            img = render_room(scene, cam, pos, R0 @ T, boxes=False).rgb
            truth = T.T @ np.array([0.0, 0.0, 1.0])
            t, u = best(track, 1, img)
            t_track.append(t)
            e_track.append(math.degrees(geodesic_distance(u, truth)))
            t, u = best(L.lines_up, 1, img, cam)
            t_each.append(t)
            e_each.append(math.degrees(geodesic_distance(u, truth)))
        a, b = np.mean(t_track[1:]), np.mean(t_each[1:])
        print(f"| {w}x{w // 2} | {frames} | {a:.3f} | {b:.3f} | {b / a:.1f}x | "
              f"{np.mean(e_track):.2f} / {max(e_track):.2f} | {np.mean(e_each):.2f} / "
              f"{max(e_each):.2f} |", flush=True)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[1024, 2048, 4096])
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--reps", type=int, default=2)
    p.add_argument("--video", type=int, default=0, metavar="FRAMES",
                   help="time a video of this many frames instead")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    cv2.setNumThreads(a.threads)
    if a.video:
        video(a.sizes, a.video)
        return
    scene = make_room(seed=3, index=3, materials="by_kind")
    pos, R0 = scene.viewpoint(0)
    T = rotation_from_axis_angle(np.array([0.0, 1.0, 0.0]), math.radians(15)) \
        @ rotation_from_axis_angle(np.array([1.0, 0.0, 0.0]), math.radians(-8))
    truth = T.T @ np.array([0.0, 0.0, 1.0])
    base = render_room(scene, Equirectangular(2048, 1024), pos, R0 @ T, boxes=False).rgb
    print("| panorama | lines_up (s) | first version (s) | ratio | error: ours / first (deg) |")
    print("|---|---|---|---|---|")
    for w in a.sizes:
        img = base if w == 2048 else cv2.resize(base, (w, w // 2), interpolation=cv2.INTER_CUBIC)
        cam = Equirectangular(w, w // 2)
        t_new, u_new = best(L.lines_up, a.reps, img, cam)
        t_ref, u_ref = best(reference_up, a.reps, img, cam)
        err = [math.degrees(geodesic_distance(u, truth)) for u in (u_new, u_ref)]
        print(f"| {w}x{w // 2} | {t_new:.2f} | {t_ref:.2f} | {t_ref / t_new:.1f}x | "
              f"{err[0]:.2f} / {err[1]:.2f} |", flush=True)


if __name__ == "__main__":
    main()
