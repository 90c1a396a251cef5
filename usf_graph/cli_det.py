"""``usf-graph train det`` and ``usf-graph eval det``: the detection commands."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np

from .cli_inputs import camera_options, camera_test


def at_least(lo: float, kind=int, above: bool = False, most: float | None = None):
    """An argparse type: a finite ``kind`` of at least ``lo`` (above it with ``above``; at
    most ``most``), so that ``--epochs -1`` or ``--lr 0`` stop at the command line."""
    def parse(text: str):
        value = kind(text)
        if not math.isfinite(value) or value < lo or (above and value == lo) or \
                (most is not None and value > most):
            want = f"{'above' if above else 'at least'} {lo}" + ("" if most is None else f" and at most {most}")
            raise argparse.ArgumentTypeError(f"must be {want}, got {text}")
        return value

    parse.__name__ = kind.__name__  # argparse names the type when kind() itself fails
    return parse


#: sizes, view counts, epochs of a model's training, batch sizes
positive_int = at_least(1)
#: counts that may be 0 (extra views, second-phase epochs, grid levels, pair layers)
count = at_least(0)
#: weights and strengths that may be 0 (a loss term's weight, a prior's strength)
nonnegative = at_least(0.0, float)
#: shares and probabilities, in [0, 1]
share = at_least(0.0, float, most=1.0)


def add_train_options(t) -> None:
    """Options of ``train det`` and ``train seg`` (their defaults: those of
    :func:`usf_graph.train.det.run` and :func:`usf_graph.train.seg.run`, read from their
    source: :mod:`usf_graph.cli_defaults`)."""
    from .cli_defaults import per_task

    g = t.add_argument_group("det and seg (the protocols on procedural rooms, or real data)")
    g.add_argument("--dataset", default="rooms", choices=["rooms", "pandora", "stanford2d3ds", "woodscape"],
                   help="procedural rooms (rendered here), or the real data: PANDORA (det), "
                        "Stanford 2D-3D-S or WoodScape's fisheyes (seg); download those first")
    g.add_argument("--size", type=positive_int, default=None,
                   help="panorama height (width 2x; fisheye and pinhole size x size); default: "
                        f"{per_task('size')} (stanford2d3ds: 256)")
    g.add_argument("--num-train", type=positive_int, default=None, help=f"rooms: training views ({per_task('num_train')})")
    g.add_argument("--num-test", type=positive_int, default=None, help=f"rooms: views per test ({per_task('num_test')})")
    g.add_argument("--lr", type=at_least(0.0, float, above=True), default=None, help=f"AdamW learning rate ({per_task('lr')})")
    g.add_argument("--scale", type=at_least(0.0, float, above=True, most=1.0), default=None,
                   help="woodscape: the images resized by this factor before lifting (0.5: "
                        "640 x 483)")
    g.add_argument("--fold", default="1", choices=["1", "2", "3", "all"],
                   help="stanford2d3ds: the area-disjoint fold, or all three")
    g.add_argument("--models", nargs="+", default=None,
                   choices=["spherical_unet", "spherical_deeplab", "planar_unet"],
                   help="seg: models to train (default: all three on rooms, the spherical U-Net "
                        "on stanford2d3ds, the spherical DeepLab on woodscape)")
    g.add_argument("--fov-epochs", type=count, default=None,
                   help="rooms: epochs of the second phase at a lower learning rate, the "
                        "spherical models' with half their batches through random fields of "
                        f"view (every model; {per_task('fov_epochs')}, 0 skips it)")
    g.add_argument("--channel-scale", type=float, default=None, metavar="S",
                   help=f"rooms: every model's channel counts times S ({per_task('channel_scale')}; 0.5 in the README's "
                        "15-minute recipes, 'make demo-seg' and 'make demo-det')")
    g.add_argument("--materials", default=None, choices=["random", "by_kind"],
                   help="rooms: every object's look drawn at random (the protocols' rooms, the "
                        "default) or a material per kind of object, as in real rooms (the same "
                        "layouts); 'eval' reads it from the checkpoint")
    g.add_argument("--gray", action="store_true",
                   help="train for a mono camera: every model, up estimate included, reads only "
                        "its images' luma (0.299 R + 0.587 G + 0.114 B), in training and in "
                        "every test; 'eval' and 'predict' read it from the checkpoint")
    u = t.add_argument_group("the spherical models' up estimate on rooms (trained first, alone)")
    u.add_argument("--up-extra", type=count, default=None,
                   help=f"cheap extra panoramas of other rooms ({per_task('up_extra')})")
    u.add_argument("--up-caps", type=share, default=None,
                   help=f"share of its batches seen through random 40-100 degree caps ({per_task('up_caps')})")
    u.add_argument("--up-epochs", type=positive_int, default=None, help=f"its epochs ({per_task('up_epochs')})")
    u.add_argument("--up-sign", type=nonnegative, default=None,
                   help=f"weight of a loss term against scoring down above up ({per_task('up_sign')}; 1 was a "
                        "lead in session 26, docs/seg_det_log.md)")


def add_device_option(p, what: str = "the model runs") -> None:
    """``--device`` of ``train``, ``eval`` and ``predict``
    (:func:`~usf_graph.train.devices.resolve_device`)."""
    p.add_argument("--device", default="cpu",
                   help=f"where {what}: cpu, cuda, cuda:N, or auto (a GPU when torch sees one); "
                        "under torchrun, cuda is each process's own GPU")


def add_eval_options(e) -> None:
    """Options of ``eval det`` and ``eval seg``: which tests, which views, which up."""
    e.add_argument("--dataset", default=None, choices=["rooms", "stanford2d3ds", "woodscape", "pandora"],
                   help="det, seg: the test data (default: what the checkpoint was trained on; "
                        "rooms for checkpoints that do not say). stanford2d3ds: the fold's test "
                        "areas; woodscape: the val list; pandora: the test split")
    e.add_argument("--fold", type=int, default=None, choices=[1, 2, 3],
                   help="stanford2d3ds: whose test areas (default: the checkpoint's fold)")
    e.add_argument("--test", nargs="+", choices=["a", "b", "c", "d", "e"], default=None,
                   help="det, seg on rooms: protocol tests (default: all; (e) is seg's)")
    e.add_argument("--size", type=positive_int, default=None,
                   help="det, seg: rooms image size, stanford2d3ds panorama height (default: "
                        "as trained)")
    e.add_argument("--num-test", type=positive_int, default=None,
                   help="det, seg on rooms: views per test (50)")
    e.add_argument("--boxes", action="store_true", help="det: also decode each true box at its centre point")
    e.add_argument("--known-up", action="store_true", help="det, seg: spherical models read each "
                   "view's true gravity, as from an IMU, not their estimate")
    e.add_argument("--up-lines", action="store_true", help="det, seg on rooms: the up estimate picks "
                   "among the Manhattan axes of each image's straight lines (any lens; "
                   "docs/up_estimate.md)")
    estimate_options(e, "det, seg: ")
    e.add_argument("--render", default=None, choices=("nearest", "soft"),
                   help="seg: how the grid's predictions reach the pixels; nearest: the nearest "
                        "point's label (the protocols'); soft: the argmax of the "
                        "probabilities blended over the three nearest points, smoother "
                        "on images finer than the grid (README, Your own images)")
    e.add_argument("--gray", action="store_true",
                   help="det, seg: the model reads the test images' luma only, as a mono "
                        "camera records them (what a colour model loses there; a checkpoint of "
                        "'train --gray' reads them so anyway)")
    e.add_argument("--camera", default=None, metavar="CALIB",
                   help="det, seg on rooms: also score through this calibrated camera, "
                        "zero-shot, the test rooms rendered through it at its size (any file "
                        "'predict --camera' reads), beside (a) unless --test names others")
    camera_options(e)
    e.add_argument("--figure", default=None, metavar="PNG",
                   help="det, seg on rooms: also draw a test view of each test: the image, "
                        "the truth and the prediction (det: the boxes on it)")
    add_device_option(e)


def estimate_options(p, scope: str = "") -> None:
    """``--level-prior`` and ``--sign-check``, the up estimate's test-time options
    (:func:`up_options` sets them), for ``eval``, ``predict`` and ``export``; ``scope``
    begins their help (where they apply)."""
    p.add_argument("--level-prior", type=nonnegative, default=None, metavar="BETA",
                   help=f"{scope}the up estimate assumes a level camera (optical axis "
                        "horizontal) with this strength (10 in the README; 0, the default, off)")
    p.add_argument("--sign-check", default=None, metavar="PATH",
                   help=f"{scope}the up estimate passes through this sign check, asked on wide "
                        "fields of view (a file of 'examples/up_sign.py --save')")


def given_or_default(args, run, keys) -> dict:
    """The options ``keys`` for ``run``: as given on the command line, else ``run``'s
    defaults."""
    from .train import defaults

    d = defaults(run)
    return {k: d[k] if getattr(args, k) is None else getattr(args, k) for k in keys}


def up_kwargs(args, run) -> dict:
    """``up_extra``, ``up_caps``, ``up_epochs`` and ``up_sign`` for a rooms protocol ``run``,
    its defaults where not given."""
    return given_or_default(args, run, ("up_extra", "up_caps", "up_epochs", "up_sign"))


def given(args, *names) -> list[str]:
    """The options among ``names`` (their attribute names) that the command line gave, as
    flags (``num_test`` -> ``--num-test``): a value, 0 included (their defaults are None),
    or a switch that is on."""
    return ["--" + n.replace("_", "-") for n in names
            if (v := getattr(args, n, None)) is not None and v is not False]


def rooms_only_options(args) -> None:
    """Refuse, on real data, the options that only the rooms protocols read (rather than
    ignore them)."""
    if args.dataset != "rooms" and args.channel_scale is not None:
        raise ValueError(f"--channel-scale is an option of the rooms protocols; on "
                         f"{args.dataset} the models train at their own channels")
    if args.dataset != "rooms" and args.materials is not None:
        raise ValueError(f"--materials is an option of the procedural rooms; {args.dataset}'s "
                         f"images are photographs")
    if args.dataset != "woodscape" and getattr(args, "scale", None) is not None:
        raise ValueError("--scale resizes WoodScape's images; give --dataset woodscape, or "
                         "--size for the others")
    rooms_only = given(args, "num_train", "num_test", "fov_epochs", "up_extra", "up_caps", "up_sign")
    if args.dataset != "rooms" and rooms_only:
        raise ValueError(f"{', '.join(rooms_only)}: options of the rooms protocols; {args.dataset} "
                         "trains on its own training split")


def refuse_options(flags: list[str], owner: str, command: str, hint: str = "") -> None:
    """Refuse ``flags`` given to ``command`` that only ``owner`` reads, rather than ignore
    them."""
    if flags:
        what = "an option" if len(flags) == 1 else "options"
        raise ValueError(f"{', '.join(flags)}: {what} of '{owner}', not of '{command}'{hint}")


def mnist_only_options(args, task: str, *keep: str) -> None:
    """Refuse the options of ``train mnist`` that ``train <task>`` does not read (all but
    ``keep``)."""
    names = ("level", "input_level", "min_level", "source", "pairs", "pair_stages")
    refuse_options(given(args, *(n for n in names if n not in keep)), "train mnist",
                   f"train {task}")


def rooms_kind(results: dict) -> str:
    """How a protocol's printed table names its rooms (and that its models saw them in gray)."""
    rooms = "rooms with materials by kind" if results.get("materials") == "by_kind" else "rooms"
    return rooms + (", seen in gray (--gray)" if results.get("gray") else "")


def run_seconds(results: dict) -> str:
    """A protocol's time as its printed table gives it: after ``--resume`` only this
    invocation's, the stages it loaded not counted."""
    return f"{results['seconds']} s" + (" since --resume" if results.get("resumed") else "")


def print_targets(results: dict, out: str | None) -> None:
    """The issue's targets of a finished rooms protocol (``usf-graph targets`` reads them
    again from the run's folder)."""
    from .train.targets import format_targets, targets

    try:
        rows = targets(results)
    except ValueError as e:  # e.g. only the planar baseline trained: the run itself is fine
        print(f"No targets: {e}\n")
        return
    print(f"The issue's targets (bold: misses):\n{format_targets({out or 'this run': rows})}\n")


def cmd_targets(args) -> int:
    from .train.targets import LEGEND, UNRECORDED, format_targets, load_results, targets, task_of

    results = {str(r): load_results(r) for r in args.runs}
    if len({task_of(res) for res in results.values()}) > 1:
        raise ValueError("these runs mix segmentation and detection: give one task's runs")
    print(format_targets({r: targets(res) for r, res in results.items()}))
    print(f"\n{LEGEND}")
    if any(task_of(res) == "det" and "drop_hidden" not in res for res in results.values()):
        print(UNRECORDED)
    return 0


def add_targets_parser(sub, fmt, full: bool = True) -> None:
    """The ``targets`` subcommand (``full=False``: its name and help only)."""
    p = sub.add_parser("targets", help="which of the rooms protocols' targets finished runs meet",
                       formatter_class=fmt,
                       description="Read runs of 'usf-graph train seg|det' on rooms and print the "
                                   "issues' targets, a column per run (usf_graph.train.targets).")
    if not full:
        return
    p.add_argument("runs", nargs="+", help="run folders (--out of train), or their results.json")
    p.set_defaults(func=cmd_targets)


def run_kwargs(args, run) -> dict:
    """The common options of ``train det|seg``, with ``run``'s defaults where not given."""
    from .train import defaults

    d = defaults(run)
    return dict(epochs=args.epochs or d["epochs"], batch_size=args.batch_size or d["batch_size"],
                seed=args.seed, progress=True, lr=args.lr or d["lr"], resume=args.resume,
                device=args.device, gray=args.gray)


def cmd_train_det(args) -> int:
    from .train import teardown_distributed
    from .train.det import format_table, run
    from .train.real import run_pandora

    if args.dataset in ("stanford2d3ds", "woodscape"):
        raise ValueError(f"{args.dataset} is a segmentation dataset here: use 'usf-graph train seg'")
    mnist_only_options(args, "det")  # the detectors read icosahedral:5
    kw = run_kwargs(args, run)
    rooms_only_options(args)
    if args.dataset == "pandora":
        res = run_pandora(root=args.root or "data/pandora", out=args.out or "runs/det_pandora",
                          **given_or_default(args, run_pandora, ("up_epochs",)), **kw)
    else:
        res = run(root=args.root or "data/rooms", out=args.out or "runs/det",
                  planar=not args.no_planar, **up_kwargs(args, run), **kw,
                  **given_or_default(args, run, ("size", "num_train", "num_test", "fov_epochs",
                                                    "channel_scale", "materials")))
    teardown_distributed()
    if not res:
        return 0
    if args.dataset == "pandora":
        print(json.dumps(res["spherical"], indent=1))
        return 0
    print(f"\nDetection on procedural {rooms_kind(res)}, trained on upright panoramas ({res['samples']['train']} "
          f"views; {res['samples']['test']} test views each; {run_seconds(res)})\n")
    for metric in ("AP50", "AP50_every_box", "AP", "usf_mAP@10"):
        print(f"{metric}:\n{format_table(res, metric)}\n")
    print_targets(res, args.out)
    if "figure" in res:
        print(f"figure: {res['figure']}")
    return 0


REAL_DATA = {"seg": ("stanford2d3ds", "woodscape"), "det": ("pandora",)}


def eval_data(ckpt, args) -> str:
    """What ``eval seg|det`` scores ``ckpt`` on: ``--dataset``, else the data it was trained
    on. A clear error for the other task's data, for options only the rooms protocols read,
    and for a model whose classes are not the data's."""
    from .datasets.woodscape import CLASSES as WOODSCAPE_CLASSES
    from .scenes import DETECTION_CLASSES, PANDORA_CLASSES, SEMANTIC_CLASSES

    data, real = args.dataset or ckpt.dataset, REAL_DATA[ckpt.task]
    if data not in ("rooms", *real):
        raise ValueError(f"{data} is not {ckpt.task} data: 'usf-graph eval {ckpt.task}' scores "
                         f"rooms or {' or '.join(real)}")
    if data != "rooms":
        rooms_only = given(args, "test", "num_test", "camera", "figure",
                           *(("size",) if data == "pandora" else ()))
        if rooms_only:
            raise ValueError(f"{', '.join(rooms_only)}: rooms options; {data} is scored on its "
                             "own test data as released")
    if data == "woodscape" and (ckpt.planar or ckpt.dataset != "woodscape"):
        raise ValueError(f"{ckpt.path} was not trained on WoodScape; its classes are not "
                         "WoodScape's 10")
    if args.fold is not None and data != "stanford2d3ds":
        raise ValueError("--fold picks Stanford 2D-3D-S's test areas; give --dataset stanford2d3ds")
    classes = {"rooms": SEMANTIC_CLASSES if ckpt.task == "seg" else DETECTION_CLASSES,
               "stanford2d3ds": SEMANTIC_CLASSES, "pandora": PANDORA_CLASSES,
               "woodscape": WOODSCAPE_CLASSES}[data]
    n = ckpt.model.config["num_classes"]
    if n != len(classes):
        raise ValueError(f"{ckpt.path} predicts {n} classes (trained on "
                         f"{ckpt.dataset}); {data} has {len(classes)}")
    if data != ckpt.dataset:
        print(f"{ckpt.path} was trained on {ckpt.dataset}; scoring it on {data}")
    return data


def ready_model(ckpt, args):
    """``ckpt``'s model on ``--device``, with the up estimate's test-time options
    (:func:`up_options`): what ``eval`` and ``predict`` run."""
    from .train import resolve_device
    from .train.provenance import announce

    announce(ckpt.path, ckpt.provenance)
    model = ckpt.model.to(resolve_device(args.device))
    up_options(model, args)
    if getattr(args, "gray", False):
        from .nn.colour import read_gray

        read_gray(model)
    return model


def up_options(model, args) -> None:
    """``eval --level-prior`` and ``--sign-check``: set on ``model``'s up estimate
    (:func:`~usf_graph.models.set_level_prior`, :func:`~usf_graph.models.set_sign_check`);
    an error if there is none to set them on, or for ``--up-lines`` without one or with
    ``--known-up``."""
    from .models import set_level_prior, set_sign_check
    from .train import model_device
    from .train.gravity import check_up_choice, require_up_estimate
    from .train.sign import load_sign_check

    check_up_choice(getattr(args, "known_up", False), getattr(args, "up_lines", False))
    for option, given in (("--up-lines", getattr(args, "up_lines", False)),
                          ("--level-prior", args.level_prior), ("--sign-check", args.sign_check)):
        if given:
            require_up_estimate(model, option)
    if args.level_prior:
        set_level_prior(model, args.level_prior)
    if args.sign_check:
        set_sign_check(model, load_sign_check(args.sign_check).to(model_device(model)))


def cmd_eval_det(args) -> int:
    from .train.checkpoints import load_protocol_model
    from .train.det import (
        PREDICT_BATCH,
        PROTOCOL,
        DetectionSet,
        box_quality,
        predict,
        protocol_sets,
        score,
    )
    from .train.gravity import format_up_report, split_up, views_up

    if args.render:
        raise ValueError("--render is segmentation's: a detector's answer is boxes")
    ckpt = load_protocol_model(args.checkpoint).require("det")
    model, cfg, planar = ready_model(ckpt, args), ckpt.config, ckpt.planar
    if eval_data(ckpt, args) == "pandora":
        from .datasets import Pandora

        if planar:
            raise ValueError("the planar detector reads the rooms' panoramas of its training "
                             "size only; score a spherical checkpoint on pandora")
        tests = {"pandora test": Pandora(args.root or "data/pandora", "test", grid=model.input_grid)}
    else:
        from .datasets import RoomsDetection

        grid = getattr(model, "input_grid", "icosahedral:5")  # the planar one reads panoramas
        own = camera_test(args, ckpt, RoomsDetection, grid)
        names = args.test or (["a"] if own is not None else list(PROTOCOL))
        if wrong := [k for k in names if k not in PROTOCOL]:  # before any rendering
            raise ValueError(f"detection has tests {', '.join(PROTOCOL)}, not {wrong[0]!r}")
        sets = protocol_sets(args.root or "data/rooms", args.size or ckpt.size, grid=grid,
                             num_train=0, num_test=args.num_test or 50,
                             seed=ckpt.rooms_seed(args.seed), materials=ckpt.materials,
                             tests=names)
        tests = {f"({k})": sets[k] for k in names} | ({} if own is None else {"(camera)": own})
    drawn: dict = {"sets": {}, "preds": {}, "ignored": {}}  # for --figure
    for k, ds in tests.items():
        data = DetectionSet.planar(ds, cfg["width"], cfg["height"]) if planar else DetectionSet.spherical(ds)
        u = split_up(model, ds, args.known_up, args.up_lines, batch_size=PREDICT_BATCH)
        found = predict(model, data, PREDICT_BATCH, up=u.up)
        r = score(found, data, model.num_classes)
        key = k.strip("()")
        drawn["sets"][key], drawn["preds"][key], drawn["ignored"][key] = ds, found, data.ignored()
        print(f"{k} {data.describe_ignored()}")
        print(f"{k} " + ", ".join(f"{m} {100 * v:.2f}" for m, v in r.items()))
        if u.estimate is not None:
            print(f"{k} " + format_up_report(u.report(views_up(ds))))
        if args.boxes:
            q = box_quality(model, data)
            print(f"{k} each true box decoded at its centre point: IoU median "
                  f"{np.median(q['iou']):.2f}, {100 * np.mean(q['iou'] >= 0.5):.0f}% at 0.5 or more; "
                  f"errors (medians): centre {np.median(q['centre_deg']):.1f} deg, log size "
                  f"{np.median(q['log_size_err']):.2f}, log aspect {np.median(q['log_aspect_err']):.2f}")
    if args.figure:
        from .viz import plot_detections

        plot_detections(drawn["sets"], drawn["preds"], args.figure, samples=(0,),
                        ignored=drawn["ignored"])
        print(f"figure: {args.figure}")
    return 0
