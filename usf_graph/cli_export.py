"""``usf-graph export seg|det``: a trained spherical segmenter or detector bound to one
camera, written as one ONNX or ``torch.export`` program for deployment
(:mod:`usf_graph.train.export`)."""

from __future__ import annotations

import json

from .cli_inputs import CAMERA_HELP, camera_from_spec, camera_options, rig_from_spec, rig_options

#: ``export det``'s decoding by default: predict's and eval's (``detect_image``)
DECODING = {"max_boxes": 100, "threshold": 0.05, "nms": 0.5}


def add_export_parser(sub, fmt, full: bool = True) -> None:
    """The ``export`` subcommand and its options (``full=False``: its name and help only)."""
    p = sub.add_parser("export", help="write a segmenter or detector bound to one camera as "
                                      "ONNX or .pt2",
                       formatter_class=fmt,
                       description="Bind a trained spherical segmenter or detector to one "
                                   "camera and write it as one program, image in, labels or "
                                   "boxes out: the lifting table, the field of view, every "
                                   "layer's coefficients and (for labels) the render table "
                                   "held as constants. ONNX runs in "
                                   "onnxruntime (checked here) or any ONNX runtime, without usf-graph; "
                                   ".pt2 is torch.export's. Checked against usf-graph on a "
                                   "procedural room rendered through the camera.")
    if not full:
        return
    from .cli_det import estimate_options, positive_int, share
    from .frontend.choices import METHODS

    p.add_argument("task", choices=["seg", "det"], help="the checkpoint's task")
    p.add_argument("checkpoint", help="a spherical checkpoint of 'usf-graph train seg|det'")
    p.add_argument("--camera", required=True, help=CAMERA_HELP)
    camera_options(p)
    p.add_argument("--rig", action="store_true",
                   help="every camera of a rig (--camera: a Kalibr camchain, Basalt "
                        "calibration, ORB-SLAM3 stereo pair or COLMAP rig), lifted onto one "
                        "sphere: the program takes one image per camera, in the file's order, "
                        "and gives one label image per camera (seg) or one set of boxes in the "
                        "rig's sphere frame (det)")
    rig_options(p, split=False)
    up = p.add_mutually_exclusive_group()
    up.add_argument("--up-input", action="store_true",
                    help="the program takes gravity's up in the camera's sphere frame (x "
                         "forward, y left, z up) as a second input, float32 [3]: an IMU")
    up.add_argument("--up", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                    help="a fixed up in the camera's sphere frame: a camera mounted at a fixed "
                         "angle to gravity (0 0 1: level)")
    estimate_options(p, "without --up/--up-input, inside the program: ")
    p.add_argument("--interpolation", default="auto", choices=("auto",) + METHODS,
                   help="how the image is lifted (as predict's)")
    g = p.add_argument_group("det: the decoding inside the program (predict's and eval's)")
    g.add_argument("--max-boxes", type=positive_int, default=None, metavar="K",
                   help="the boxes output holds the K best peaks; the detections are the rows "
                        f"with score > 0 (default: {DECODING['max_boxes']})")
    g.add_argument("--threshold", type=share, default=None,
                   help=f"a peak's lowest score (default: {DECODING['threshold']})")
    g.add_argument("--nms", type=share, default=None, metavar="IOU",
                   help=f"greedy NMS per class at this spherical IoU (1: none; default: "
                        f"{DECODING['nms']})")
    p.add_argument("--no-check", action="store_true",
                   help="skip running the written file against usf-graph on a rendered room")
    p.add_argument("--out", required=True, metavar="PATH",
                   help="the program: .onnx (needs usf-graph[export]) or .pt2; without "
                        "--up/--up-input it holds the model's own up estimate")
    # what ready_model reads from predict's options: export traces on the CPU
    p.set_defaults(func=cmd_export, device="cpu")


def cmd_export(args) -> int:
    from .cli_det import ready_model
    from .train.checkpoints import load_protocol_model
    from .train.export import export_format, export_model

    export_format(args.out)  # a wrong suffix before the checkpoint loads
    given = {k: getattr(args, k) for k in DECODING if getattr(args, k) is not None}
    if args.task == "seg" and given:
        raise ValueError(f"{', '.join('--' + k.replace('_', '-') for k in given)}: a detector's "
                         "decoding; a segmenter's program gives labels")
    opts = {**DECODING, **given}
    up = "input" if args.up_input else args.up
    for option, value in (("--level-prior shapes", args.level_prior),
                          ("--sign-check corrects", args.sign_check)):
        if value and up is not None:
            raise ValueError(f"{option} the model's up estimate, which --up and --up-input replace")
    if args.distance is not None and not args.rig:
        raise ValueError("--distance stitches the cameras of a --rig; one camera needs none")
    if args.rig:
        camera = rig_from_spec(args.camera, args.fov, args.image_mask, args.key, args.distance)
    else:
        camera = camera_from_spec(args.camera, args.key, args.fov, args.image_mask)
    ckpt = load_protocol_model(args.checkpoint).require(args.task, spherical=True)
    model = ready_model(ckpt, args)
    decoding = {} if args.task == "seg" else \
        dict(k=opts["max_boxes"], threshold=opts["threshold"], nms=None if opts["nms"] >= 1 else opts["nms"])
    info = export_model(model, camera, args.out, up=up, interpolation=args.interpolation,
                        check=not args.no_check, **decoding)
    print(f"wrote {info['path']} ({info['format']}, {info['bytes'] / 1e6:.1f} MB) in "
          f"{info['export_s']:.1f} s")
    k = opts["max_boxes"]
    outputs = ", ".join(info["outputs"][:-1]) + " uint8 [H, W] (255: unseen)" \
        if args.task == "seg" else (f"boxes float32 [{k}, 5] (radians), classes int64 [{k}], "
                                    f"scores float32 [{k}] (the detections: score > 0)")
    print(f"inputs: {', '.join(info['inputs'])}; outputs: {outputs}, {info['outputs'][-1]} float32 [3]")
    if "check" in info:
        c = info["check"]
        agree = (f"{100 * c['agree']:.2f}% of {c['pixels_seen']} pixels agree" if args.task == "seg"
                 else f"{c['matched']} of {c['detections']} detections found alike")
        print(f"check on a room rendered through the camera: {agree} with usf-graph, ups "
              f"{c['up_angle_deg']:.3f} deg apart; {1000 * c['frame_s']:.0f} ms a frame here "
              f"(loaded in {c['load_s']:.1f} s)")
    if info["format"] == "ONNX" and not args.rig:
        print(f"run it on frames without usf-graph: python examples/deploy_onnx.py {info['path']} "
              f"FRAME.png{' --up X Y Z' if up == 'input' else ''}")
    print(json.dumps({k: v for k, v in info.items() if k != "check"}, default=str))
    return 0
