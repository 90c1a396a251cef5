"""Re-imaging video frames: a :class:`~usf_graph.frontend.Reimager` built once and applied
to every frame, against the first ``render`` (the geometry and a float64 gather on every
call, kept here as it was), and against a bare ``cv2.remap`` of the same maps (the floor).

    python benchmarks/reimage.py [--sizes 1024,2048,4096] [--reps 5] [--threads 2]

Two jobs: a tilted panorama leveled (a panorama turned into a panorama at its own size),
and a dual-fisheye frame (two 190-degree Kannala-Brandt fisheyes, each ``size / 2``
square) stitched into a ``size x size / 2`` panorama (:class:`RigReimager`). Frames are
uint8 RGB. The ratio over 100 frames counts the build once. The last column compares the
two results (``cv2.remap`` places a pixel to 1/32 and rounds its own way).
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np
import torch
from conv import timeit as best_of  # noqa: E402  (benchmarks/ is the script's folder)

from usf_graph import cameras
from usf_graph.frontend import Reimager, RigReimager, blend_weights
from usf_graph.frontend.interpolation import bilinear_entries, valid_entries
from usf_graph.geometry import level_rotation


def first_render(image, cam_src, cam_dst):
    """``render`` as it was before the Reimager: everything on every call."""
    rays, valid = cam_dst.lens_normal_map()
    pos = np.where(valid[..., None], rays, 1.0).reshape(-1, 3)
    uv, seen = cam_src.sees(pos)
    seen &= valid.ravel()
    idx, w = bilinear_entries(cam_src, np.nan_to_num(uv, nan=-1.0), seen)
    w = valid_entries(cam_src, idx, w)
    flat = torch.as_tensor(image).double().reshape(-1, image.shape[-1])
    w = torch.as_tensor(w)[..., None]
    out = torch.where(w > 0, flat[torch.as_tensor(idx)] * w, 0).sum(1)
    return out.round().clamp(0, 255).to(torch.uint8).reshape(cam_dst.height, cam_dst.width, -1).numpy()


def first_render_rig(images, cams, cam_dst):
    """``render_rig`` as it was: each camera through :func:`first_render`, then blended."""
    rays, valid = cam_dst.lens_normal_map()
    pos = np.where(valid[..., None], rays, 1.0).reshape(-1, 3)
    parts, seen = [], []
    for im, cam in zip(images, cams):
        both = first_render(np.concatenate([im, np.full(im.shape[:2] + (1,), 255, np.uint8)], -1), cam, cam_dst)
        parts.append(both[..., :-1].reshape(len(pos), -1).astype(np.float64))
        seen.append(both[..., -1].ravel() > 127)
    w, _ = blend_weights(cams, pos, np.stack(seen))
    return sum(wk[:, None] * p for wk, p in zip(w, parts)).round().astype(np.uint8)


def jobs(size: int, rng):
    pano = cameras.Equirectangular(size, size // 2)
    tilted = pano.turned(level_rotation(np.array([0.25, -0.15, 0.95])))
    half = size // 2
    fish = cameras.KannalaBrandt(half / 3.4, half / 3.4, (half - 1) / 2, (half - 1) / 2, half, half,
                                 k=(0.0, 0.0, 0.0, 0.0)).with_fov(190)
    back = fish.turned(np.diag([-1.0, -1.0, 1.0]))
    frame = (rng.random((size // 2, size, 3)) * 255).astype(np.uint8)
    fishes = [(rng.random((half, half, 3)) * 255).astype(np.uint8) for _ in range(2)]
    return {
        f"panorama {size}x{size // 2} leveled": (
            lambda: Reimager(tilted, pano), lambda r: r(frame),
            lambda: first_render(frame, tilted, pano), frame),
        f"dual fisheye 2x{half}x{half} -> panorama {size}x{size // 2}": (
            lambda: RigReimager([fish, back], pano), lambda r: r(fishes),
            lambda: first_render_rig(fishes, [fish, back], pano), fishes[0]),
    }


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--sizes", default="1024,2048,4096", help="panorama widths, comma-separated")
    p.add_argument("--reps", type=int, default=5)
    p.add_argument("--threads", type=int, default=2)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    cv2.setNumThreads(a.threads)
    rng = np.random.default_rng(0)
    print(f"{a.threads} threads, best of {a.reps} (the first render: one run)")
    print("| job | build (s) | per frame (ms) | cv2.remap floor (ms) | first render per frame (s) "
          "| first / per frame | first / (build + per frame), 100 frames "
          "| largest difference, grey levels (pixels that differ) |")
    print("|---|---|---|---|---|---|---|---|")
    for size in (int(s) for s in a.sizes.split(",")):
        for name, (build, apply, first, src) in jobs(size, rng).items():
            t = time.perf_counter()
            r = build()
            built = time.perf_counter() - t
            warm = best_of(lambda r=r, f=apply: f(r), a.reps)
            remap = r._parts[0]._fast if hasattr(r, "_parts") else r._fast
            floor = best_of(lambda m=remap, src=src: cv2.remap(src, *m.maps, cv2.INTER_LINEAR,
                                                      borderMode=m.border_mode), a.reps)
            t = time.perf_counter()
            before = first()
            old = time.perf_counter() - t
            diff = np.abs(apply(r).astype(int).ravel() - before.astype(int).ravel())
            print(f"| {name} | {built:.2f} | {1e3 * warm:.1f} | {1e3 * floor:.1f} | {old:.2f} "
                  f"| {old / warm:.0f}x | {100 * old / (built + 100 * warm):.1f}x "
                  f"| {diff.max()} ({100 * (diff > 0).mean():.1f}%) |", flush=True)


if __name__ == "__main__":
    main()
