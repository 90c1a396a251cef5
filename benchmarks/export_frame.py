"""Time one frame of an exported segmenter or detector (``usf-graph export``) next to the
same model in usf-graph, on the same image, in the same run.

    python benchmarks/export_frame.py [--task seg|det] [--lens fisheye|pinhole|panorama]
                                      [--size 512] [--threads 2] [--reps 5]
                                      [--channel-scale 1.0]

The protocols' spherical DeepLab or detector (untrained: the cost does not depend on the
weights; the detector's heatmaps raised and spread so that it decodes distinct peaks) bound to a ``size x
size`` image of the protocols' 190-degree fisheye or 90-degree pinhole (a ``2 size x
size`` panorama). Rows, ms per frame (image in, labels in the camera's pixels or boxes
out, the camera's tables built before timing):

* usf-graph (:func:`~usf_graph.train.apply.segment_image`,
  :func:`~usf_graph.train.apply.detect_image`), up given and its estimate: the fast path
  (sparse products), what ``predict`` runs;
* usf-graph in the plain forms (:func:`usf_graph.tracing.plain`), up given: what the
  exporters trace, run eagerly;
* the ONNX program (up an input) in onnxruntime on ``--threads`` threads;
* the ``.pt2`` program (its own up estimate) through ``torch.export.load``.

Each exported file is also checked against usf-graph on a rendered room (the share of
pixels that agree, or of detections found alike), and its size and export time are
printed.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import torch
from timing import best_time

from usf_graph import tracing
from usf_graph.scenes import make_room
from usf_graph.scenes.lenses import protocol_cameras
from usf_graph.scenes.render import render
from usf_graph.train import apply
from usf_graph.train.det import make_detector
from usf_graph.train.export import export_model, load_exported
from usf_graph.train.seg import make_model

LENSES = {"fisheye": "fisheye190", "pinhole": "pinhole90", "panorama": "equirectangular"}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--task", default="seg", choices=["seg", "det"])
    p.add_argument("--lens", default="fisheye", choices=sorted(LENSES))
    p.add_argument("--size", type=int, default=512)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--reps", type=int, default=5)
    p.add_argument("--channel-scale", type=float, default=1.0)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    if args.task == "seg":
        net, answer = make_model("spherical_deeplab", channel_scale=args.channel_scale).eval(), apply.segment_image
    else:
        net, answer = make_detector(channel_scale=args.channel_scale).eval(), apply.detect_image
        with torch.no_grad():  # CenterNet's prior keeps an untrained detector's scores at
            # 0.01, and its scores tie: raised and spread, so that it decodes distinct peaks
            net.head.weight[: net.num_classes].mul_(300.0)
            net.head.bias[: net.num_classes].fill_(-1.0)
    cam = protocol_cameras(args.size)[LENSES[args.lens]]
    image = render(make_room(0), cam, boxes=False).rgb
    up = np.array([0.0, 0.0, 1.0])

    with torch.no_grad():
        answer(net, image, cam, up=up)  # the camera's tables, as a first frame
        rows = {"usf-graph, up given": best_time(lambda: answer(net, image, cam, up=up), args.reps),
                "usf-graph, its up estimate": best_time(lambda: answer(net, image, cam), args.reps)}

        def plain():
            with tracing.plain():
                return answer(net, image, cam, up=up)
        rows["usf-graph plain forms, up given"] = best_time(plain, args.reps)
    files = []
    with tempfile.TemporaryDirectory() as d:
        for name, given, key in ((f"{args.task}.onnx", "input", "ONNX in onnxruntime, up given"),
                                 (f"{args.task}.pt2", None, ".pt2 (torch.export), its up estimate")):
            info = export_model(net, cam, Path(d) / name, up=given)
            run = load_exported(info["path"], threads=args.threads)
            feed = up if given == "input" else None
            rows[key] = best_time(lambda run=run, feed=feed: run(image, feed), args.reps)
            files.append((name, info))
    base = rows["usf-graph, up given"]
    print(f"\n{type(net).__name__} (channel scale {args.channel_scale}) on icosahedral:5, "
          f"{cam.width}x{cam.height} {LENSES[args.lens]}, {args.threads} threads, best of {args.reps}\n")
    print("| per frame | ms | / usf-graph, up given |\n|---|---|---|")
    for k, t in rows.items():
        print(f"| {k} | {1000 * t:.1f} | {t / base:.2f} |")
    what = "pixels agreeing" if args.task == "seg" else "detections found alike"
    print(f"\n| file | MB | export s | {what} with usf-graph |\n|---|---|---|---|")
    for name, info in files:
        c = info["check"]
        alike = f"{100 * c['agree']:.2f}%" if args.task == "seg" else f"{c['matched']} of {c['detections']}"
        print(f"| {name} | {info['bytes'] / 1e6:.1f} | {info['export_s']:.1f} | {alike} |")


if __name__ == "__main__":
    main()
