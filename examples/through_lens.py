"""How close to the panorama can a model get through a narrow lens, if it is trained for it?

The rooms protocols test the fisheye (c) and the pinhole (d) zero-shot. This script gives
the bound a zero-shot model is measured against: it takes a protocol model after its
first phase (panoramas only; ``<checkpoint without .pt>/last.pt``) and trains it on
through that lens's own field of view instead of the protocol's second phase: every batch
of the training panoramas cut to what the lens sees, turned about gravity at random (a
level camera stays level; ``--turn so3`` mounts it at random instead), the labels or boxes
it hides left out, the normalizations frozen, at the second phase's learning rate
(:func:`usf_graph.train.fov.second_phase` with ``ThroughRandomFields(camera=...)``). Then
it scores (a) and the lens's test, given the true up and with the estimate (without and
with the level-camera prior, ``--level-prior``): mIoU on pixels (``train seg``) or AP50 (``train det``). It writes the trained model and
``results.json`` under ``--out``.

It is not zero-shot: the model has seen the test lens's field of view in training, which
makes it the lens-supervised reference, and the way to adapt a panorama model to a lens
you know without rendering new data.

    .venv/bin/python examples/through_lens.py runs/seg/spherical_deeplab.pt --test d
    .venv/bin/python examples/through_lens.py runs/det/spherical.pt --test d --epochs 12

About 13 minutes (seg, 8 epochs; det, 12 epochs) on 2 cores once the protocol's rooms
are rendered (``data/rooms``). ``--device cuda`` trains and scores on a GPU (the detector's 12
epochs with the rooms rendered there: about 2 minutes on an H100).
"""

from __future__ import annotations

import argparse
import json
from functools import partial
from pathlib import Path

from usf_graph.models import set_level_prior
from usf_graph.train import defaults, det, load_checkpoint, save_checkpoint, seg, seg_eval
from usf_graph.train.checkpoints import load_protocol_model
from usf_graph.train.fov import second_phase
from usf_graph.train.gravity import views_up


def _seg(net, args, size, level):
    sets = seg.protocol_sets(args.root, size, level, args.num_train, args.num_test, args.seed,
                             tests=("a", args.test), progress=args.progress,
                             materials=args.materials)
    train = sets["train"]
    cut = seg.ThroughRandomFields(train.grid.pos, 1.0, args.seed, camera=sets[args.test].camera,
                                  turn=args.turn)
    step = partial(seg.segmentation_step, class_weight=seg.balanced_weights(train, args.balance))
    second_phase(net, train, args.epochs, args.out, "through the lens", cut=cut,
                 batch_size=defaults(seg.run)["batch_size"], seed=args.seed,
                 progress=args.progress, step=step, device=args.device)

    def metric(known):
        res, _ = seg_eval.evaluate_protocol(net, sets, ("a", args.test), args.progress, known_up=known)
        return {k: r["mIoU"] for k, r in res.items()}

    return metric, "mIoU on pixels"


def _det(net, args, size, _level):
    sets = det.protocol_sets(args.root, size, num_train=args.rendered, num_test=args.num_test,
                             seed=args.seed, progress=args.progress, materials=args.materials)
    data = {k: det.DetectionSet.spherical(sets[k]) for k in ("train", "a", args.test)}
    train = data["train"].first(args.num_train)
    cut = det.ThroughRandomFields(train, sets["train"].grid.pos, 1.0, args.seed,
                                  camera=sets[args.test].camera, turn=args.turn)
    second_phase(net, train, args.epochs, args.out, "through the lens", cut=cut,
                 batch_size=defaults(det.run)["batch_size"], seed=args.seed,
                 progress=args.progress, step=det.detection_step, device=args.device)

    def metric(known):
        found = {k: det.predict(net, data[k], progress=False, up=views_up(sets[k]) if known else None)
                 for k in ("a", args.test)}
        return {k: det.score(f, data[k], net.num_classes)["AP50"] for k, f in found.items()}

    return metric, "AP50"


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint", help="a rooms protocol's spherical checkpoint; its first "
                   "phase is read from <checkpoint without .pt>/last.pt")
    p.add_argument("--test", default="d", choices=["c", "d"], help="d: pinhole 90, c: fisheye 190")
    p.add_argument("--epochs", type=int, default=8)
    p.add_argument("--turn", default="yaw", choices=["yaw", "so3"],
                   help="yaw: the lens level, turned about gravity; so3: mounted at random")
    p.add_argument("--out", default=None, help="default: <checkpoint without .pt>_through_<test>")
    p.add_argument("--root", default="data/rooms")
    p.add_argument("--seed", type=int, default=None,
                   help="the rooms' seed (default: the checkpoint's own)")
    p.add_argument("--num-train", type=int, default=None,
                   help="training views (default: the protocol's, 400 seg, 200 det)")
    p.add_argument("--rendered", type=int, default=defaults(det.run)["up_train"],
                   help="det: training rooms rendered (default: as many as the protocol "
                        "renders for its up estimate, 400)")
    p.add_argument("--num-test", type=int, default=50)
    p.add_argument("--size", type=int, default=None,
                   help="panorama height (default: the checkpoint's, or det's 128)")
    p.add_argument("--level-prior", type=float, default=10.0,
                   help="also score the estimate with this level-camera prior (0: skip)")
    p.add_argument("--balance", type=float, default=0.5, help="seg: the class weights' power")
    p.add_argument("--device", default=None,
                   help="train and score on this device (cpu, cuda, auto; default cpu)")
    p.add_argument("--no-progress", dest="progress", action="store_false")
    args = p.parse_args(argv)
    ckpt = Path(args.checkpoint)
    first = ckpt.with_suffix("") / "last.pt"
    if not first.exists():
        raise SystemExit(f"{first}: no first-phase state next to {ckpt}; train the protocol with "
                         "`usf-graph train seg` or `train det` first")
    saved = load_protocol_model(ckpt, weights=False).require(spherical=True)
    net, size = saved.model, args.size or saved.size
    args.seed, args.materials = saved.rooms_seed(args.seed), saved.materials
    run = _seg if saved.task == "seg" else _det
    args.num_train = args.num_train or defaults(seg.run if run is _seg else det.run)["num_train"]
    args.rendered = max(args.rendered, args.num_train)
    if getattr(net, "gravity", None) is None:
        raise SystemExit(f"{ckpt}: the model has no up estimate to keep frozen")
    load_checkpoint(first, net)
    net.gravity.requires_grad_(False)
    args.out = Path(args.out or f"{ckpt.with_suffix('')}_through_{args.test}")
    metric, unit = run(net, args, size, saved.config.get("level", 5))
    res = {"test": args.test, "epochs": args.epochs, "turn": args.turn,
           "true up": metric(True), "estimate": metric(False)}
    if args.level_prior:
        set_level_prior(net, args.level_prior)
        res["estimate, level prior"] = metric(False)
    print(f"{unit} after {args.epochs} epochs through the lens of ({args.test}), turned by {args.turn}:")
    for k in ("true up", "estimate", "estimate, level prior"):
        if k in res:
            print(f"  {k:22s} " + "  ".join(f"({t}) {100 * v:6.2f}" for t, v in res[k].items()))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(res, indent=1))
    save_checkpoint(args.out / "model.pt", net.cpu(), saved.config, res)
    return res


if __name__ == "__main__":
    main()
