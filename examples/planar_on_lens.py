"""How close to its panorama score does a planar network get on a narrow lens it is trained for?

The lens-supervised reference for the planar baseline, next to ``through_lens.py``'s for the
spherical models: a :class:`~usf_graph.models.PlanarUNet` trained from scratch on the test
lens's own images (``--test d``: the 90-degree pinhole, ``c``: the 190-degree fisheye) of
``--num-train`` training rooms of the segmentation protocol, each seen once from that
room's camera pose, with the protocol's loss (class weights ``--balance``), batch size and
learning rate. It scores the lens's test set on its own pixels (mIoU, the protocol's
metric) and writes the model and ``results.json`` under ``--out``. Compare with the
protocol's planar U-Net on (a): what seeing only the lens's part of each room costs a
network that has trained on exactly that.

    .venv/bin/python examples/planar_on_lens.py --test d              # 400 rooms x 30 epochs
    .venv/bin/python examples/planar_on_lens.py --test d --num-train 1200 --epochs 10

About 20 minutes each on 2 cores, the pinhole views rendered (about 70 s per 400 rooms).
"""

from __future__ import annotations

import argparse
import json
from functools import partial
from pathlib import Path

from usf_graph.datasets import RoomsSegmentation
from usf_graph.models import PlanarUNet
from usf_graph.scenes.materials import MATERIALS
from usf_graph.train import defaults, fit, save_checkpoint, seed_everything, seg, seg_eval
from usf_graph.train.engine import scaled_channels
from usf_graph.train.seg_metrics import score


def main(argv=None) -> dict:
    protocol = defaults(seg.run)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--test", default="d", choices=["c", "d"], help="d: pinhole 90, c: fisheye 190")
    p.add_argument("--num-train", type=int, default=protocol["num_train"],
                   help="training rooms, one view each")
    p.add_argument("--epochs", type=int, default=30)
    p.add_argument("--size", type=int, default=protocol["size"],
                   help="the protocol's size: lens images size x size")
    p.add_argument("--level", type=int, default=protocol["level"],
                   help="the grid the rooms are stored on")
    p.add_argument("--balance", type=float, default=protocol["balance"],
                   help="the class weights' power")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--channel-scale", type=float, default=1.0,
                   help="the U-Net's channel counts times this (0.5: the 15-minute recipe's)")
    p.add_argument("--root", default="data/rooms")
    p.add_argument("--materials", default="random", choices=MATERIALS,
                   help="the rooms' looks (usf_graph.scenes.materials)")
    p.add_argument("--num-test", type=int, default=protocol["num_test"])
    p.add_argument("--out", default=None, help="default: runs/planar_on_<test>_s<seed>")
    p.add_argument("--no-progress", dest="progress", action="store_false")
    a = p.parse_args(argv)
    test = seg.protocol_sets(a.root, a.size, a.level, num_train=0, num_test=a.num_test,
                             seed=a.seed, tests=(a.test,), progress=a.progress,
                             materials=a.materials)[a.test]
    train = RoomsSegmentation(a.root, "train", camera=test.camera, grid=test.grid,
                              num_scenes=a.num_train, seed=a.seed, progress=a.progress,
                              materials=a.materials)
    kind = "_by_kind" if a.materials == "by_kind" else ""
    out = Path(a.out or f"runs/planar_on_{a.test}_s{a.seed}{kind}")
    seed_everything(a.seed)
    net = PlanarUNet(len(seg.SEMANTIC_CLASSES), **scaled_channels(PlanarUNet, a.channel_scale))
    step = partial(seg.segmentation_step, class_weight=seg.balanced_weights(train, a.balance))
    fit(net, train, None, epochs=a.epochs, batch_size=protocol["batch_size"], lr=protocol["lr"],
        seed=a.seed, log_dir=out, config=net.config, progress=a.progress,
        name=f"planar on ({a.test})", step=step)
    pixels, _ = seg_eval.predict(net, test, progress=a.progress, pano=test.camera)  # its own image
    res = {"test": a.test, "num_train": a.num_train, "epochs": a.epochs, "seed": a.seed,
           "materials": a.materials, "channel_scale": a.channel_scale,
           **{k: v for k, v in score(pixels, test).items() if k in ("mIoU", "mAcc")}}
    print(f"planar U-Net trained on ({a.test})'s own images of {a.num_train} rooms x {a.epochs} "
          f"epochs: mIoU {100 * res['mIoU']:.2f}, mAcc {100 * res['mAcc']:.2f} on its pixels")
    (out / "results.json").write_text(json.dumps(res, indent=1))
    save_checkpoint(out / "model.pt", net, {"model": "planar_unet", "size": a.size, **net.config}, res)
    return res


if __name__ == "__main__":
    main()
