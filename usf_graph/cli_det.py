"""``usf-graph train det`` and ``usf-graph eval det``: the detection commands."""

from __future__ import annotations

import json


def add_train_options(t, d: dict) -> None:
    """Options of ``train det`` (``d``: the defaults of :func:`usf_graph.train.det.run`)."""
    g = t.add_argument_group("det (the detection protocol)")
    g.add_argument("--dataset", default="rooms", choices=["rooms", "pandora"],
                   help="procedural rooms (rendered here) or PANDORA (download it first)")
    g.add_argument("--size", type=int, default=d["size"],
                   help="rooms: panorama height (width 2x; fisheye and pinhole size x size)")
    g.add_argument("--num-train", type=int, default=d["num_train"], help="rooms: training views")
    g.add_argument("--num-test", type=int, default=d["num_test"], help="rooms: views per test")
    g.add_argument("--lr", type=float, default=d["lr"], help="AdamW learning rate")


def cmd_train_det(args) -> int:
    from .train import teardown_distributed
    from .train.det import format_table, run, run_pandora

    kw = dict(epochs=args.epochs or 24, batch_size=args.batch_size or 8, seed=args.seed,
              progress=True, lr=args.lr)
    if args.dataset == "pandora":
        res = run_pandora(root=args.root or "data/pandora", out=args.out or "runs/det_pandora", **kw)
    else:
        res = run(root=args.root or "data/rooms", out=args.out or "runs/det", size=args.size,
                  num_train=args.num_train, num_test=args.num_test, planar=not args.no_planar, **kw)
    teardown_distributed()
    if not res:
        return 0
    if args.dataset == "pandora":
        print(json.dumps(res["spherical"], indent=1))
        return 0
    print(f"\nDetection on procedural rooms, trained on upright panoramas ({res['samples']['train']} "
          f"views; {res['samples']['test']} test views each; {res['seconds']} s)\n")
    for metric in ("AP50", "AP", "usf_mAP@10"):
        print(f"{metric}:\n{format_table(res, metric)}\n")
    if "figure" in res:
        print(f"figure: {res['figure']}")
    return 0


def cmd_eval_det(args) -> int:
    from .models import PlanarDetector, SphericalDetector
    from .train import load_checkpoint
    from .train.det import PROTOCOL, DetectionSet, predict, protocol_sets, score

    blob = load_checkpoint(args.checkpoint)
    cfg = blob["config"]
    planar = "height" in cfg
    model = (PlanarDetector if planar else SphericalDetector).from_config(cfg)
    model.load_state_dict(blob["state_dict"])
    sets = protocol_sets(args.root or "data/rooms", args.size, num_train=0,
                         num_test=args.num_test, seed=args.seed)
    for k in args.test or list(PROTOCOL):
        ds = sets[k]
        data = DetectionSet.planar(ds, cfg["width"], cfg["height"]) if planar else DetectionSet.spherical(ds)
        r = score(predict(model, data), data, model.num_classes)
        print(f"({k}) " + ", ".join(f"{m} {100 * v:.2f}" for m, v in r.items()))
    return 0
