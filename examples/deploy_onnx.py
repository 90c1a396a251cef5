"""Run a segmenter or detector exported by ``usf-graph export seg|det`` on a camera's
frames, with onnxruntime, numpy and OpenCV only: what a robot's process needs, without
usf-graph or PyTorch.

    python examples/deploy_onnx.py deploy/fisheye_seg.onnx frame.png [more.png ...]
                                   [--up 0 0 1] [--out overlays]

Each frame (any image OpenCV reads, BGR on disk) goes in as RGB; ``--up`` (gravity's up in
the camera's sphere frame: x forward, y left, z up) is required when the program takes
one (``--up-input`` at export) and refused when it does not. For a segmenter it writes
``<out>/<frame>_labels.png`` (the class of each pixel, 255 where the camera sees nothing)
and ``<out>/<frame>_overlay.png`` (the frame with the classes in colour), and prints each
frame's largest classes; for a detector ``<out>/<frame>_boxes.json`` (each detection's
class, score and box, in radians in the sphere frame and in PANDORA's degrees) and its best
detections. Classes are named from the file's own metadata. A rig's file (one image per
camera) is not for this script: feed its session one image per camera.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort


def palette(n: int) -> np.ndarray:
    """``[n, 3]`` uint8 RGB colours, evenly spread in hue."""
    hsv = np.stack([np.arange(n) * 180 // max(n, 1), np.full(n, 200), np.full(n, 230)], 1)
    return cv2.cvtColor(hsv.astype(np.uint8)[None], cv2.COLOR_HSV2RGB)[0]


def segmented(labels, bgr, unseen: int, colours, stem: Path, classes: list) -> str:
    """Write a segmenter's labels and an overlay; the three largest classes, as text."""
    cv2.imwrite(f"{stem}_labels.png", labels)
    seen = labels != unseen
    overlay = bgr.copy()
    tint = colours[np.where(seen, labels, 0)][..., ::-1]  # RGB palette -> BGR image
    overlay[seen] = (0.45 * bgr[seen] + 0.55 * tint[seen]).astype(np.uint8)
    cv2.imwrite(f"{stem}_overlay.png", overlay)
    share = np.bincount(labels[seen], minlength=len(classes)) / max(int(seen.sum()), 1)
    return ", ".join(f"{classes[k]} {100 * share[k]:.0f}%" for k in np.argsort(-share)[:3] if share[k] > 0)


def detected(boxes, cls, scores, stem: Path, classes: list) -> str:
    """Write a detector's detections (the rows scoring above 0, best first) as JSON; the
    three best, as text. PANDORA's degrees negate the longitude and the roll (its
    longitude grows to the right of the panorama)."""
    kept = scores > 0
    found = [{"class": classes[int(c)], "score": round(float(s), 4),
              "box_rad": [round(float(v), 6) for v in b],
              "pandora_deg": [round(float(v), 3) for v in np.degrees(b * [-1, 1, 1, 1, -1])]}
             for b, c, s in zip(boxes[kept], cls[kept], scores[kept])]
    Path(f"{stem}_boxes.json").write_text(json.dumps(found, indent=1))
    return ", ".join(f"{d['class']} {d['score']:.2f}" for d in found[:3]) + \
        (f" ({len(found)} detections)" if found else "")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("model", help="an .onnx file written by 'usf-graph export seg|det'")
    p.add_argument("frames", nargs="+", help="the camera's images")
    p.add_argument("--up", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                   help="gravity's up in the camera's sphere frame, for a program that takes it")
    p.add_argument("--out", default="overlays", help="folder for the label images and overlays")
    args = p.parse_args(argv)

    session = ort.InferenceSession(args.model, providers=["CPUExecutionProvider"])
    meta = session.get_modelmeta().custom_metadata_map
    if "classes" not in meta:
        sys.exit(f"{args.model} has no usf-graph metadata (class names): write it again with "
                 "'usf-graph export'")
    classes, task = json.loads(meta["classes"]), meta.get("task", "seg")
    inputs = session.get_inputs()
    if len([i for i in inputs if i.name != "up"]) != 1:
        sys.exit(f"{args.model} is a rig's program (inputs {[i.name for i in inputs]}): feed its "
                 "session one image per camera")
    takes_up = any(i.name == "up" for i in inputs)
    if takes_up != (args.up is not None):
        sys.exit(f"{args.model} {'takes' if takes_up else 'holds its own'} up: "
                 f"{'give --up X Y Z' if takes_up else 'drop --up'}")
    h, w = inputs[0].shape[:2]
    colours = palette(len(classes))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for path in args.frames:
        # the pixels as stored: a JPEG's EXIF orientation turns them for display only
        bgr = cv2.imread(path, cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
        if bgr is None:
            sys.exit(f"cannot read {path} as an image")
        if bgr.shape[:2] != (h, w):
            sys.exit(f"{path} is {bgr.shape[1]}x{bgr.shape[0]}, the program's camera "
                     f"{w}x{h}: export again for this calibration")
        feeds = {inputs[0].name: cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)}
        if takes_up:
            feeds["up"] = np.asarray(args.up, np.float32)
        *answer, up_read = session.run(None, feeds)
        stem = Path(path).stem
        found = segmented(answer[0], bgr, int(meta["unseen"]), colours, out / stem, classes) \
            if task == "seg" else detected(*answer, out / stem, classes)
        print(f"{stem}: {found or 'nothing seen'} (up read {np.round(up_read, 3).tolist()})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
