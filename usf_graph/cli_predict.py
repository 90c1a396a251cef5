"""``usf-graph predict seg|det``: a trained spherical model on your own camera's image."""

from __future__ import annotations

import json
import warnings
from functools import partial
from pathlib import Path

import numpy as np

from .cli_bags import bag_camera, bag_options, imu_up, predict_rig_bag
from .cli_inputs import (
    CAMERA_HELP,
    alpha_masked,
    camera_from_spec,
    camera_options,
    check_panorama_videos,
    eye_option,
    is_panorama_spec,
    read_image,
    rig_from_spec,
    rig_options,
)
from .fileio import atomic_write, write_image
from .videos import VIDEO_SUFFIXES, is_video, split_frame
from .videos import frames as video_frames

#: the score from which ``predict det`` draws and lists boxes
MIN_SCORE = 0.3


def add_predict_parser(sub, fmt, full: bool = True) -> None:
    """The ``predict`` subcommand and its options (``full=False``: its name and help only)."""
    p = sub.add_parser("predict", help="run a trained seg or det model on your own image",
                       formatter_class=fmt,
                       description="Lift an image through its camera onto a trained spherical "
                                   "model's grid and write the answer in the camera's terms: "
                                   "seg, a label image in its pixels and a figure; det, "
                                   "spherical boxes (JSON, PANDORA's degrees) drawn on it.")
    if not full:
        return
    from .cli_det import add_device_option, at_least, estimate_options, positive_int, share
    from .frontend.choices import METHODS

    p.add_argument("task", choices=["seg", "det"], help="the checkpoint's task")
    p.add_argument("checkpoint", help="a spherical checkpoint of 'usf-graph train seg|det'")
    p.add_argument("image", nargs="+",
                   help="RGB image(s) of the one camera (any format OpenCV reads, or .npy), "
                        "videos (" + ", ".join(VIDEO_SUFFIXES) + ": each frame an image, "
                        "<video>_<frame>_* outputs) or ROS bags (.bag, a ROS 2 bag's folder, "
                        ".db3, .mcap: the images of --topic); several: frames, the model "
                        "loaded once (with --rig: one image per camera)")
    p.add_argument("--every", type=positive_int, default=1, metavar="N",
                   help="videos and bags: every N-th frame (1: all)")
    p.add_argument("--topic", default=None, action="append",
                   help="ROS bags: the image topic (sensor_msgs/Image or CompressedImage); "
                        "default: the bag's only one. With --rig, once per camera in the rig's "
                        "order (default: a Kalibr camchain's rostopics)")
    bag_options(p, "each frame's up")
    eye_option(p)
    p.add_argument("--camera", default=None,
                   help=CAMERA_HELP + "; for a ROS bag, default: its camera_info beside the "
                        "image topic")
    camera_options(p)
    p.add_argument("--rig", action="store_true",
                   help="the images are one frame of a rig's cameras (--camera: a Kalibr "
                        "camchain, Basalt calibration, ORB-SLAM3 stereo pair or COLMAP rig), "
                        "one per camera in its order, lifted onto one sphere")
    rig_options(p)
    p.add_argument("--up", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                   help="gravity's up in the camera's sphere frame (x forward, y left, z up; "
                        "with --rig the rig's, cam0's), e.g. from an IMU; default: the model's "
                        "own estimate")
    p.add_argument("--up-lines", action="store_true",
                   help="the up estimate picks among the Manhattan axes of the image's straight "
                        "lines (any lens, a rig's cameras together: docs/up_estimate.md); not "
                        "with --up")
    estimate_options(p)
    add_device_option(p)
    p.add_argument("--interpolation", default="auto", choices=("auto",) + METHODS,
                   help="how the image is lifted; auto: area where the image is over twice as "
                        "fine as the grid (no aliasing), else bilinear as in training")
    p.add_argument("--render", default=None, choices=("nearest", "soft"),
                   help="seg: how the grid's predictions reach the pixels; nearest: the nearest "
                        "point's label (the default; the protocols'); soft: the argmax of the "
                        "probabilities blended over the three nearest points, smoother "
                        "on images finer than the grid (README, Your own images)")
    p.add_argument("--min-score", type=share, default=None,
                   help=f"det: boxes drawn and listed from this score (default: {MIN_SCORE}; "
                        "the JSON keeps every box from 0.05)")
    p.add_argument("--video", default=None, metavar="AVI|MP4",
                   help="also write every frame's picture (seg: the image beside its labels; "
                        "det: the boxes drawn) into this video, e.g. for a bag or a video")
    p.add_argument("--video-fps", type=at_least(0.0, float, above=True), default=None,
                   metavar="FPS", help="--video's frame rate (default: 10)")
    p.add_argument("--out", default="predictions", metavar="DIR",
                   help="folder for <image name>_labels.png and _seg.png (seg), or "
                        "_boxes.json and _boxes.png (det)")
    p.set_defaults(func=cmd_predict)


def _report_up(info: dict) -> str:
    if info["source"] == "none":
        return "up: not read (this model has no up estimate)"
    u = ", ".join(f"{v:+.3f}" for v in info["up"])
    if info["source"] == "given":
        return f"up: ({u}), given"
    flag = " UNSURE: give --up from an IMU if you have one" if info["unsure"] else ""
    how = ("picked by the estimate among the image's straight-line axes" if info["source"] == "lines"
           else "estimated")
    note = f" ({info['lines']})" if "lines" in info else ""
    return f"up: ({u}), {how}, margin {info['margin']:.2f}{note}{flag}"


def _up_arg(args):
    """``--up`` or ``--up-lines`` as :func:`~usf_graph.train.apply.segment_image`'s ``up``."""
    if args.up_lines and args.up is not None:
        raise ValueError("--up-lines lets the estimate pick among the image's straight lines: "
                         "not with --up (a known up needs no estimate)")
    return "lines" if args.up_lines else args.up


def cmd_predict(args) -> int:
    from .bags import is_bag
    from .cli_det import ready_model
    from .train.apply import class_names
    from .train.checkpoints import load_protocol_model

    stems = [Path(p).stem for p in args.image]
    if len(set(stems)) < len(stems):
        twice = sorted({s for s in stems if stems.count(s) > 1})
        raise ValueError(f"several images are named {twice}: their outputs would overwrite "
                         "each other in --out; predict them in separate runs")
    if args.distance is not None and not args.rig:
        raise ValueError("--distance stitches the cameras of a --rig; one camera needs none")
    streams = [p for p in args.image if is_video(p) or is_bag(p)]
    rig_bag = args.rig and len(args.image) == 1 and is_bag(args.image[0])
    if args.split and not args.rig:
        raise ValueError("--split cuts each frame into a rig's cameras' images: add --rig")
    if args.split and any(is_bag(p) for p in args.image):
        raise ValueError("--split cuts images and video frames; a rig's bag has a topic per camera")
    if args.rig and streams and not rig_bag and not args.split:
        raise ValueError("--rig reads one image per camera, or one ROS bag with a topic per "
                         "camera; not videos, nor bags among images (a video whose frames "
                         "hold every camera side by side: add --split)")
    if args.every != 1 and not streams:
        raise ValueError("--every picks a video's or a bag's frames; no video (" +
                         ", ".join(VIDEO_SUFFIXES) + ") or ROS bag was given")
    if args.topic is not None and not any(is_bag(p) for p in args.image):
        raise ValueError("--topic picks a ROS bag's image topic; no bag was given")
    if args.topic and len(args.topic) > 1 and not args.rig:
        raise ValueError("several --topic are a rig's cameras (--rig); one camera reads one")
    if args.camera is None and not all(is_bag(p) for p in args.image):
        raise ValueError("give the camera's calibration with --camera (only a ROS bag can "
                         "bring its own, as camera_info)")
    if args.imu is not None and (not all(is_bag(p) for p in args.image) or args.up is not None
                                 or args.up_lines):
        raise ValueError("--imu reads up from a ROS bag's accelerometer: every input a bag, and "
                         "not with --up or --up-lines")
    if args.imu is None and args.imu_up != "accel":
        raise ValueError("--imu-up says how to read --imu's messages: give --imu TOPIC")
    if args.camera is None and args.key is not None:
        raise ValueError("--key picks a camera in --camera's file; a bag's camera_info holds one")
    _up_arg(args)  # its errors before anything loads
    check_panorama_videos(args)
    if args.render and args.task != "seg":
        raise ValueError("--render is segmentation's: a detector's answer is boxes")
    if args.min_score is not None and args.task != "det":
        raise ValueError("--min-score is detection's: a segmenter labels every pixel")
    if args.video_fps is not None and args.video is None:
        raise ValueError("--video-fps is --video's frame rate: give --video OUT.mp4 too")
    ckpt = load_protocol_model(args.checkpoint).require(args.task, spherical=True)
    model = ready_model(ckpt, args)  # loaded once for every image
    names = class_names(args.task, model.config["num_classes"])
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    video = None
    if args.video is not None:
        from .viz import FrameVideo

        video = FrameVideo(args.video, **({} if args.video_fps is None else {"fps": args.video_fps}))
    run = partial(_predict_seg if args.task == "seg" else _predict_det, video=video)
    try:
        _predict_all(run, model, names, out, args, rig_bag, streams)
    finally:
        if video is not None:
            video.close()
    if video is not None:
        print(f"wrote {args.video} ({video.frames} frames at {video.fps:g} fps)")
    return 0


def _predict_all(run, model, names, out: Path, args, rig_bag: bool, streams) -> None:
    """Every image, frame or rig frame of ``args.image`` through ``run``."""
    if rig_bag:  # a rig's recording: one image per camera and frame, one sphere each
        predict_rig_bag(run, model, names, out, args)
        return
    if args.split:  # every image or video frame holds the rig's cameras side by side
        _predict_split(run, model, names, out, args)
        return
    if args.rig:  # one frame of the rig: an image per camera, one sphere
        images = [read_image(p) for p in args.image]
        run(model, [Path(p).stem for p in args.image], args.image, images,
            _rig_cameras(images, args.image, args), names, out, args)
        return
    from .cameras import frame_key

    several = len(args.image) > 1 or bool(streams)
    calibrated = {}  # the calibration, read once per image size or bag (frames share it)
    topic = args.topic[0] if args.topic else None
    imu = imu_up(args)
    for stem, source, image, bag, stamp in _inputs(args.image, args.every, topic, args.eye):
        if several:
            print(f"== {source}")
        up = None if imu is None else imu(bag, stamp)
        # a panorama's crop may come from its file, a transforms.json frame's camera too
        own = args.camera is not None and (is_panorama_spec(args.camera) or (
            args.key is None and frame_key(args.camera, source) is not None))
        key = (image.shape, source if own else None) if args.camera is not None else bag
        if key not in calibrated:
            calibrated[key] = bag_camera(bag, topic, args) if args.camera is None else \
                camera_from_spec(args.camera, args.key, args.fov, args.image_mask, image.shape,
                                 source)
        cam = alpha_masked(calibrated[key], image, source)
        run(model, [stem], [source], [image], cam, names, out, args, up=up)


def _inputs(paths, every: int = 1, topic: str | None = None, eye: str | None = None):
    """``(stem, source, RGB image, bag or None, stamp in ns or None)`` of every image, and of every ``every``-th
    frame of every video (stem ``<video>_<frame index>``, source ``<video>#<frame index>``;
    with ``eye``, that eye's panorama of a stereo 360 video's frames)
    and ROS bag (source ``<bag>#<topic>@<stamp in ns>``), read one at a time so that a long
    recording never sits in memory."""
    from .bags import frames, is_bag

    for path in paths:
        if is_bag(path):
            name = Path(path).stem
            for f in frames(path, topic, every):
                yield (f"{name}_{f.index:06d}", f"{path}#{f.topic}@{f.stamp_ns}", f.image, path,
                       f.stamp_ns)
            continue
        if not is_video(path):
            yield Path(path).stem, str(path), read_image(path), None, None
            continue
        for i, rgb in video_frames(path, every, eye):
            yield f"{Path(path).stem}_{i:06d}", f"{path}#{i}", rgb, None, None


def _predict_split(run, model, names, out: Path, args) -> None:
    """``predict --rig --split``: each image or video frame cut into the rig's cameras'
    images (:func:`~usf_graph.videos.split_frame`), one sphere each; the rig fitted to
    the first frame (``--distance auto``: chosen there) and kept for the rest."""
    from .cameras import load_rig

    count = len(load_rig(args.camera, key=args.key))
    rig = None
    for stem, source, image, _, _ in _inputs(args.image, args.every, eye=args.eye):
        parts = split_frame(image, count, args.camera)
        if rig is None:
            rig = rig_from_spec(args.camera, args.fov, args.image_mask, args.key, args.distance,
                                parts)
        if len(args.image) > 1 or is_video(args.image[0]):
            print(f"== {source}")
        sources = [f"{source}[{n}]" for n in rig]
        cams = {n: alpha_masked(c, im, s) for (n, c), im, s in zip(rig.items(), parts, sources)}
        run(model, [f"{stem}_{n}" for n in rig], sources, parts, cams, names, out, args)


def _rig_cameras(images, sources, args):
    """The rig of ``--rig``'s images (one per camera), each camera masked by its image's
    alpha channel (:func:`_alpha_masked`)."""
    rig = rig_from_spec(args.camera, args.fov, args.image_mask, args.key, args.distance, images)
    if len(images) != len(rig):
        raise ValueError(f"--rig: {args.camera} has {len(rig)} cameras ({', '.join(rig)}) but "
                         f"{len(images)} images were given, one per camera in that order")
    return {n: alpha_masked(c, im, p) for (n, c), im, p in zip(rig.items(), images, sources)}


def _predict_seg(model, stems, sources, images, cam, names, out: Path, args, up=None,
                 video=None) -> None:
    from .scenes import colourize
    from .train.apply import UNSEEN, segment_image

    r = segment_image(model, images if args.rig else images[0], cam,
                      up=_up_arg(args) if up is None else up,
                      interpolation=args.interpolation, render=args.render or "nearest")
    print(_report_up(r))
    pictures = []
    for stem, image, lab in zip(stems, images, r["labels"] if args.rig else [r["labels"]]):
        pictures.append(np.hstack([_as_uint8(image), colourize(lab)]))
        seen = lab != UNSEEN
        shares = np.bincount(lab[seen], minlength=len(names)) / max(int(seen.sum()), 1)
        top = np.argsort(-shares)[:5]
        print(f"{stem}: " + ", ".join(f"{names[c]} {100 * shares[c]:.1f}%" for c in top
                                      if shares[c] > 0))
        write_image(out / f"{stem}_labels.png", lab)
        _seg_figure(_as_uint8(image), lab, out / f"{stem}_seg.png", names)
        print(f"wrote {out / f'{stem}_labels.png'} (class index per pixel, {UNSEEN}: unseen) "
              f"and {out / f'{stem}_seg.png'}")
    if video is not None:  # a rig's cameras one above the other
        video.add(_stacked(pictures, axis=0))


def _predict_det(model, stems, sources, images, cam, names, out: Path, args, up=None,
                 video=None) -> None:
    import cv2

    from .train.apply import detect_image
    from .viz import draw_boxes

    r = detect_image(model, images if args.rig else images[0], cam,
                     up=_up_arg(args) if up is None else up,
                     interpolation=args.interpolation)
    print(_report_up(r))
    stem = stems[0]
    _write_boxes(r, names, out / f"{stem}_boxes.json", sources,
                 args.camera or "the bag's camera_info")
    min_score = MIN_SCORE if args.min_score is None else args.min_score
    keep = r["scores"] >= min_score
    if keep.any():
        print(f"{'class':>14} score  [lon, lat, fov_x, fov_y, gamma] in degrees, as in the JSON")
    for b, c, s in zip(_pandora(r["boxes"][keep]), r["classes"][keep], r["scores"][keep]):
        print(f"{names[c]:>14} {s:.2f}   [" + ", ".join(f"{v:.1f}" for v in b) + "]")
    print(f"{int(keep.sum())} of {len(keep)} boxes score {min_score:g} or more")
    cams = list(cam.values()) if args.rig else [cam]
    pictures = []
    for s, image, c in zip(stems, images, cams):  # each camera draws what it sees
        scale = max(1, round(512 / max(c.width, c.height)))  # small images enlarged to about 512
        drawn = draw_boxes(_as_uint8(image), c, r["boxes"][keep],
                           [names[k] for k in r["classes"][keep]], scale=scale)
        write_image(out / f"{s}_boxes.png", cv2.cvtColor(drawn, cv2.COLOR_RGB2BGR))
        pictures.append(drawn)
    if video is not None:  # a rig's cameras side by side
        video.add(_stacked(pictures, axis=1))
    print(f"wrote {out / f'{stem}_boxes.json'} and " +
          ", ".join(str(out / f"{s}_boxes.png") for s in stems))


def _stacked(pictures: list, axis: int) -> np.ndarray:
    """RGB pictures one above the other (``axis`` 0) or side by side (1), each scaled to the
    first's width (or height)."""
    import cv2

    ref = pictures[0].shape[1 - axis]
    fit = []
    for p in pictures:
        n = p.shape[1 - axis]
        if n != ref:
            size = (ref, round(p.shape[0] * ref / n)) if axis == 0 else (round(p.shape[1] * ref / n), ref)
            p = cv2.resize(p, size, interpolation=cv2.INTER_AREA)
        fit.append(p)
    return np.concatenate(fit, axis)


def _as_uint8(image: np.ndarray) -> np.ndarray:
    """The RGB of an image that predict accepted, as uint8 for drawing on."""
    from .frontend.image import to_uint8
    from .train.apply import rgb_channels

    with warnings.catch_warnings():  # said once already, when the image was read
        warnings.simplefilter("ignore")
        return np.ascontiguousarray(to_uint8(rgb_channels(image)))


def _pandora(boxes) -> np.ndarray:
    """Boxes ``[D, 5]`` (radians, our frame) in PANDORA's stored form (degrees, its signs),
    turned to ``|gamma| <= 45`` (:func:`~usf_graph.ops.canonical_boxes`)."""
    from .ops import canonical_boxes, to_pandora

    return to_pandora(canonical_boxes(boxes)).reshape(-1, 5) if len(boxes) else np.zeros((0, 5))


def _write_boxes(r: dict, names, path: Path, images, camera) -> None:
    """The detections as JSON, boxes in PANDORA's stored form (degrees, its signs)."""
    bbox = _pandora(r["boxes"])
    doc = {"images": [str(p) for p in images], "camera": str(camera),
           "frame": "the camera's (or rig's) sphere frame (x forward, y left, z up); bbox as PANDORA "
                    "stores it: [lon, lat, fov_x, fov_y, gamma] in degrees, lon growing to the "
                    "right, gamma counter-clockwise as displayed",
           "up": {k: v for k, v in r.items() if k in ("up", "source", "margin", "unsure", "lines")},
           "interpolation": r["interpolation"],
           "detections": [{"category": names[c], "category_index": int(c), "score": float(s),
                           "bbox": [float(v) for v in b]}
                          for b, c, s in zip(bbox, r["classes"], r["scores"])]}
    atomic_write(path, lambda f: f.write(json.dumps(doc, indent=1)), mode="w")


def _seg_figure(rgb: np.ndarray, labels: np.ndarray, path: Path, names) -> None:
    from .scenes import PALETTE, colourize
    from .viz import contact_sheet

    present = np.unique(labels[labels < len(names)])
    contact_sheet([[("image", rgb), ("predicted labels", colourize(labels))]], path,
                  legend={names[c]: PALETTE[c] for c in present})
