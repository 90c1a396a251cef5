"""A 360 camera's video, stitched: two back-to-back 190-degree fisheyes 0.1 m apart (the
Kalibr rig fixture) film a procedural room while turning, and every frame holds both
circles side by side, as a dual-fisheye camera writes them. ``usf-graph render --split``
stitches the video into an equirectangular one, with the baseline ignored (at infinity)
and at the distance where the two cameras agree best on their overlap (``--distance
auto``, chosen on the first frame); each frame is compared with the room rendered as a
panorama from the rig's centre (mean absolute difference in grey levels, over the whole
panorama and on the seam: the points within 5 degrees of where the two fields meet).

    .venv/bin/python examples/stitch_video.py --out runs/stitch_video [--frames 8]

About half a minute on 2 cores. Writes ``dual.avi`` (the camera's video), ``pano_inf.avi``
and ``pano_auto.avi`` (the stitched ones), ``results.json`` and ``stitch.png`` (the first
frame: the camera's, stitched, and the truth).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import cv2
import numpy as np
from tqdm.auto import tqdm

from usf_graph import cameras, scenes, videos
from usf_graph.cameras.rig import rig_centre
from usf_graph.cli import main as usf_graph
from usf_graph.geometry import rotation_from_axis_angle
from usf_graph.viz import contact_sheet

RIG = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "kalibr_rig.yaml"


def decoded(path) -> list:
    return [f for _, f in videos.frames(path)]


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="runs/stitch_video")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--turn", type=float, default=10.0, help="degrees of yaw per frame")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--width", type=int, default=1024, help="the stitched panorama's width")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rig = {n: c.with_fov(190) for n, c in cameras.load_rig(RIG).items()}
    centre, _ = rig_centre(rig)
    rig = {n: c.with_position(c.position - centre) for n, c in rig.items()}  # about its centre
    room = scenes.make_room(seed=args.seed, index=0, materials="by_kind")
    position, R0 = room.viewpoint(0)
    pano = cameras.Equirectangular(args.width, args.width // 2)
    cam0 = next(iter(rig.values()))
    video = cv2.VideoWriter(str(out / "dual.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10,
                            (2 * cam0.width, cam0.height))
    truth = []
    for k in tqdm(range(args.frames), desc="filming the room"):
        R = R0 @ rotation_from_axis_angle([0.0, 0.0, 1.0], math.radians(args.turn * k))
        shots = [scenes.render(room, c, position, R, boxes=False).rgb for c in rig.values()]
        video.write(np.ascontiguousarray(np.concatenate(shots, 1)[..., ::-1]))
        truth.append(scenes.render(room, pano, position, R, boxes=False).rgb)
    video.release()
    common = [str(out / "dual.avi"), "--camera", str(RIG), "--fov", "190", "--split",
              "--to", f"equirectangular:{pano.width}x{pano.height}"]
    for name, flags in (("inf", []), ("auto", ["--distance", "auto"])):
        if usf_graph(["render", *common, *flags, "--out", str(out / f"pano_{name}.avi")]) != 0:
            raise SystemExit("usf-graph render failed")
    rays = pano.lens_normal_map()[0]
    seam = np.abs(rays[..., 0]) < math.sin(math.radians(5))  # cam0 looks along +x, cam1 along -x
    results = {}
    for name in ("inf", "auto"):
        got = decoded(out / f"pano_{name}.avi")
        diff = [np.abs(g.astype(float) - t.astype(float)).mean(-1) for g, t in zip(got, truth)]
        results[name] = {"frames": len(got), "mean": float(np.mean([d.mean() for d in diff])),
                         "seam": float(np.mean([d[seam].mean() for d in diff]))}
        print(f"stitched {'at infinity' if name == 'inf' else 'at the chosen distance'}: "
              f"{results[name]['mean']:.1f} grey levels from the room on average, "
              f"{results[name]['seam']:.1f} on the seam ({len(got)} frames)")
    (out / "results.json").write_text(json.dumps(results, indent=1))
    first = decoded(out / "dual.avi")[0]
    rows = [[("the camera's frame (both fisheyes)", first)],
            [("stitched at infinity", decoded(out / "pano_inf.avi")[0])],
            [("stitched at the chosen distance", decoded(out / "pano_auto.avi")[0])],
            [("the room from the rig's centre", truth[0])]]
    contact_sheet(rows, out / "stitch.png")
    print(f"wrote {out / 'stitch.png'} and the videos in {out}")
    return results


if __name__ == "__main__":
    main()
