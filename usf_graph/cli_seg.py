"""``usf-graph train seg`` and ``usf-graph eval seg``: the segmentation commands."""

from __future__ import annotations

import json

from .cli_det import (
    eval_data,
    given_or_default,
    mnist_only_options,
    print_targets,
    ready_model,
    rooms_kind,
    rooms_only_options,
    run_kwargs,
    run_seconds,
    up_kwargs,
)
from .cli_inputs import camera_test


def cmd_train_seg(args) -> int:
    from .train import teardown_distributed
    from .train.real import run_stanford, run_woodscape
    from .train.seg import MODELS, format_table, run

    if args.dataset == "pandora":
        raise ValueError("PANDORA is a detection dataset: use 'usf-graph train det'")
    mnist_only_options(args, "seg", "level")
    if args.no_planar and "planar_unet" in (args.models or ()):
        raise ValueError("--no-planar and --models planar_unet: give one of them")
    kw = run_kwargs(args, run)
    rooms_only_options(args)
    if args.dataset == "stanford2d3ds":
        folds = (1, 2, 3) if args.fold == "all" else (int(args.fold),)
        res = run_stanford(root=args.root or "data/stanford2d3ds", out=args.out or "runs/seg_stanford",
                           folds=folds, models=tuple(args.models or ("spherical_unet",)),
                           **given_or_default(args, run_stanford, ("size", "level", "up_epochs")), **kw)
    elif args.dataset == "woodscape":
        if args.size is not None:
            raise ValueError("--size: WoodScape's images keep their shape; --scale resizes them")
        res = run_woodscape(root=args.root or "data/woodscape", out=args.out or "runs/seg_woodscape",
                            models=tuple(args.models or ("spherical_deeplab",)),
                            **given_or_default(args, run_woodscape, ("scale", "level", "up_epochs")), **kw)
    else:
        models = args.models or [m for m in MODELS if not (args.no_planar and m == "planar_unet")]
        res = run(root=args.root or "data/rooms", out=args.out or "runs/seg",
                  models=tuple(models), **up_kwargs(args, run), **kw,
                  **given_or_default(args, run, ("size", "level", "num_train", "num_test", "fov_epochs",
                                                    "channel_scale", "materials")))
    teardown_distributed()
    if not res:
        return 0
    if args.dataset == "stanford2d3ds":
        print(json.dumps({m: res[m]["mean"] for m in res if isinstance(res[m], dict) and "mean" in res[m]},
                         indent=1))
        return 0
    if args.dataset == "woodscape":
        print(f"\nWoodScape val ({res['samples']['test']} images; trained on "
              f"{res['samples']['train']} from {res['fields_of_view']} fields of view; {run_seconds(res)})")
        for m in ("spherical_unet", "spherical_deeplab"):
            if m in res:
                print(format_woodscape(m, res[m]))
        return 0
    print(f"\nSegmentation on procedural {rooms_kind(res)}, trained on upright panoramas ({res['samples']['train']} "
          f"views; {res['samples']['test']} test views each; {run_seconds(res)})\n")
    for metric in ("mIoU", "mAcc"):
        print(f"{metric} (camera pixels):\n{format_table(res, metric)}\n")
    print_targets(res, args.out)
    if "figure" in res:
        print(f"figure: {res['figure']}")
    return 0


def format_woodscape(name: str, r: dict) -> str:
    """A WoodScape score (:func:`~usf_graph.train.real.evaluate_fields`) in two lines."""
    cams = ", ".join(f"{c} {100 * v:.2f}" for c, v in r["cameras"].items())
    return (f"{name}: mIoU {100 * r['mIoU']:.2f}, mAcc {100 * r['mAcc']:.2f}, sphere_mIoU "
            f"{100 * r['sphere_mIoU']:.2f}, per_image_mIoU {100 * r['per_image_mIoU']:.2f}\n"
            f"{name} per camera: mIoU {cams}")


def cmd_eval_seg(args) -> int:
    from .cameras import Equirectangular
    from .train.checkpoints import load_protocol_model
    from .train.gravity import format_up_report
    from .train.seg import protocol_sets
    from .train.seg_eval import PROTOCOL, evaluate_protocol, evaluate_set

    ckpt = load_protocol_model(args.checkpoint).require("seg")
    model, name = ready_model(ckpt, args), ckpt.name
    render = args.render or "nearest"
    if render != "nearest" and ckpt.planar:
        raise ValueError("--render soft blends a spherical model's probabilities on its grid; "
                         "a planar model labels the panorama's pixels itself")
    level = ckpt.config.get("level", 5)
    data = eval_data(ckpt, args)
    if data == "woodscape":
        from .datasets import WoodScape
        from .datasets.woodscape import CLASSES
        from .train.real import evaluate_fields

        test = WoodScape(args.root or "data/woodscape", "val", grid=f"icosahedral:{level}",
                         scale=ckpt.scale or 0.5)
        r = evaluate_fields(model, test, args.known_up, desc=f"{name} val", render=render,
                            names=CLASSES)
        print(format_woodscape(name, r))
        return 0
    if data == "stanford2d3ds":
        from .datasets import Stanford2D3DS

        fold = args.fold or ckpt.fold or 1
        size = args.size or (ckpt.size if ckpt.dataset == "stanford2d3ds" else 256)
        test = Stanford2D3DS(args.root or "data/stanford2d3ds", fold, "test",
                             grid=f"icosahedral:{level}", size=size)
        res = {f"fold {fold} test": evaluate_set(model, test, f"{name} fold {fold}", args.known_up,
                                                 up_lines=args.up_lines, render=render)[0]}
    else:
        from .datasets import RoomsSegmentation

        own = camera_test(args, ckpt, RoomsSegmentation, f"icosahedral:{level}")
        tests = args.test or (["a"] if own is not None else list(PROTOCOL))
        sets = protocol_sets(args.root or "data/rooms", args.size or ckpt.size, level, num_train=0,
                             num_test=args.num_test or 50, seed=ckpt.rooms_seed(args.seed), tests=tests,
                             materials=ckpt.materials)
        res, preds = evaluate_protocol(model, sets, tests, name=name, known_up=args.known_up,
                                       up_lines=args.up_lines, render=render)
        res = {f"({k})": r for k, r in res.items()}
        if own is not None:  # a planar model sees it re-imaged as its training panorama
            pano = Equirectangular(2 * ckpt.size, ckpt.size)
            res["(camera)"], preds["camera"] = evaluate_set(
                model, own, f"{name} (camera)", args.known_up, up_lines=args.up_lines,
                render=render, pano=pano)
            sets["camera"] = own
        if args.figure:
            from .viz import plot_segmentation

            plot_segmentation(sets, {name: preds}, args.figure)
    for k, r in res.items():
        print(f"{k} " + ", ".join(f"{m} {100 * r[m]:.2f}" for m in
                                  ("mIoU", "mAcc", "sphere_mIoU", "per_image_mIoU") if m in r))
        if "up" in r:
            print(f"{k} " + format_up_report(r["up"]))
    if args.figure:
        print(f"figure: {args.figure}")
    return 0
