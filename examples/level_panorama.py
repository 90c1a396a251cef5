"""Level a tilted panorama from its straight lines, and check it against the truth.

A procedural room is rendered as an equirectangular panorama from a camera pitched and
rolled by known angles (a 360 camera held askew). ``frontend.lines.lines_up`` finds up
from the room's straight lines (no training), ``geometry.level_rotation`` turns it to +z,
and ``frontend.render`` re-images the panorama through the turned camera, which is what
``usf-graph render --level`` does. The room rendered level along the same heading is the
truth. Writes ``tilted.png`` (the input, for ``usf-graph render``), and ``level.jpg``: the
tilted panorama, the leveled one and the truth, one above the other.

    .venv/bin/python examples/level_panorama.py --out runs/level
    .venv/bin/python examples/level_panorama.py --survey --size 512   # how reliable, 2 min
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import cv2
import numpy as np

from usf_graph.cameras import Equirectangular
from usf_graph.frontend import render as reimage
from usf_graph.frontend.lines import lines_up
from usf_graph.geometry import geodesic_distance, level_rotation, rotation_from_axis_angle
from usf_graph.scenes import make_room, render


def run(out="runs/level", pitch: float = 15.0, roll: float = -8.0, size: int = 512,
        seed: int = 3, index: int = 3) -> dict:
    """Render, level and compare; returns the errors (degrees, grey levels) it prints."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cam = Equirectangular(size, size // 2)
    scene = make_room(seed=seed, index=index, materials="by_kind")
    pos, R0 = scene.viewpoint(0)
    T = rotation_from_axis_angle(np.array([0.0, 1.0, 0.0]), math.radians(pitch)) \
        @ rotation_from_axis_angle(np.array([1.0, 0.0, 0.0]), math.radians(roll))
    true_up = T.T @ np.array([0.0, 0.0, 1.0])  # gravity in the tilted camera's sphere frame
    tilted = render(scene, cam, pos, R0 @ T, boxes=False).rgb
    up = lines_up(tilted, cam)
    R = level_rotation(up)
    leveled = reimage(tilted, cam.turned(R), cam)  # the camera mounted level, re-imaged
    truth = render(scene, cam, pos, R0 @ T @ level_rotation(true_up).T, boxes=False).rgb
    res = {"tilt_deg": math.degrees(geodesic_distance(true_up, [0.0, 0.0, 1.0])),
           "up_error_deg": math.degrees(geodesic_distance(up, true_up)),
           "pixel_error_tilted": float(np.abs(tilted.astype(float) - truth).mean()),
           "pixel_error_leveled": float(np.abs(leveled.astype(float) - truth).mean())}
    print(f"tilted {res['tilt_deg']:.1f} degrees; up from the lines {res['up_error_deg']:.2f} degrees "
          f"off; mean |difference| to the level room: {res['pixel_error_tilted']:.1f} tilted, "
          f"{res['pixel_error_leveled']:.1f} leveled (grey levels of 255)")
    cv2.imwrite(str(out / "tilted.png"), tilted[..., ::-1])
    rows = []
    for img, text in ((tilted, "tilted"), (leveled, "leveled from its straight lines"),
                      (truth, "the room rendered level")):
        row = np.ascontiguousarray(img[..., ::-1])
        cv2.putText(row, text, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 2)
        rows.append(row)
    cv2.imwrite(str(out / "level.jpg"), np.concatenate(rows, 0), [cv2.IMWRITE_JPEG_QUALITY, 85])
    print(f"wrote {out / 'tilted.png'} and {out / 'level.jpg'}")
    return res


def survey(size: int = 512, rooms: int = 12, max_tilt: float = 20.0, seed: int = 11) -> dict:
    """How far up from the lines (:func:`lines_up`) lies from gravity through three lenses:
    ``rooms`` rooms (even ones with random materials, whose textures have straight
    stripes of their own; odd ones with materials by kind), each seen from its first
    viewpoint pitched and rolled by up to ``max_tilt`` degrees. ``size``: the pinhole's and
    the fisheye's side, the panorama's height. Returns each lens's errors in degrees
    (``nan`` where the lines refuse)."""
    from usf_graph.cameras import Pinhole
    from usf_graph.scenes.lenses import protocol_cameras

    lenses = {"panorama": Equirectangular(2 * size, size),
              "fisheye 190": protocol_cameras(size)["fisheye190"],
              "pinhole 90": Pinhole(size / 2, size / 2, (size - 1) / 2, (size - 1) / 2, size, size)}
    rng = np.random.default_rng(seed)
    tilts = rng.uniform(-max_tilt, max_tilt, (rooms, 2))
    errors = {}
    for name, cam in lenses.items():
        errors[name] = []
        for k in range(rooms):
            scene = make_room(seed=seed, index=k, materials="by_kind" if k % 2 else "random")
            pos, R = scene.viewpoint(0)
            R = R @ rotation_from_axis_angle(np.array([0.0, 1.0, 0.0]), math.radians(tilts[k, 0])) \
                @ rotation_from_axis_angle(np.array([1.0, 0.0, 0.0]), math.radians(tilts[k, 1]))
            try:
                up = lines_up(render(scene, cam, pos, R, boxes=False).rgb, cam)
                errors[name].append(math.degrees(geodesic_distance(up, R[2])))
            except ValueError:
                errors[name].append(math.nan)
        e = np.array(errors[name])
        print(f"{name:12s} within 1 degree on {int((e < 1).sum())} of {rooms}, within 5 on "
              f"{int((e < 5).sum())}; errors " + " ".join(f"{v:.1f}" for v in e))
    return errors


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default="runs/level")
    p.add_argument("--pitch", type=float, default=15.0, help="degrees, nose down")
    p.add_argument("--roll", type=float, default=-8.0, help="degrees")
    p.add_argument("--size", type=int, default=512, help="panorama width (--survey: its height, "
                   "and the pinhole's and fisheye's side)")
    p.add_argument("--survey", action="store_true",
                   help="instead: how far the lines' up lies from gravity on 12 rooms tilted "
                        "by up to 20 degrees, through a panorama, a fisheye and a pinhole")
    args = p.parse_args(argv)
    if args.survey:
        survey(args.size)
    else:
        run(args.out, args.pitch, args.roll, args.size)


if __name__ == "__main__":
    main()
