"""Where a checkpoint's up estimate fails: its errors by how much floor and ceiling a view shows.

A level 90-degree pinhole looks along the viewpoint's random yaw, so some of the protocol's
pinhole views face a wall from a metre or two and show no floor or ceiling at all; the
image then holds little to tell up from the wall's own horizontal direction. This sorts a
test's views by the share of their pixels labelled floor or ceiling and counts, per bin,
the views on which the estimate is over 60 degrees off. It also scores the checkpoint on
the views that show under 2% floor and ceiling, on the others, and on all, with the
estimate and with the views' true gravity: AP50 for a detector (the protocol's rule),
mIoU on the camera's pixels for a segmenter (one confusion matrix per subset).

    .venv/bin/python examples/up_by_view.py runs/s35_det15/spherical.pt --test d
    .venv/bin/python examples/up_by_view.py runs/seg_15min/spherical_deeplab.pt --test d

About a minute once the protocol's rooms are rendered (``data/rooms``); session 36's
numbers: docs/up_estimate.md, "Which pinhole views fail".
"""

from __future__ import annotations

import argparse

import numpy as np

from usf_graph.scenes import SEMANTIC_CLASSES
from usf_graph.train import det, seg, seg_eval
from usf_graph.train.checkpoints import load_protocol_model
from usf_graph.train.det_metrics import coco_ap
from usf_graph.train.gravity import GROSS_DEGREES, up_errors, views_up
from usf_graph.train.seg_metrics import confusion_matrix, scores

BINS = (0.0, 0.02, 0.10, 0.25, 1.01)  # shares of a view's pixels that are floor or ceiling
WALL = BINS[1]  # under this, a "wall close-up"
FLIPPED = 120.0  # degrees: an estimate this far off took down for up


def floor_and_ceiling(ds) -> np.ndarray:
    """Each view's share of pixels labelled floor or ceiling, ``[S]``."""
    lab = ds.label_image.numpy().reshape(len(ds), -1)
    keep = np.isin(lab, [SEMANTIC_CLASSES.index("floor"), SEMANTIC_CLASSES.index("ceiling")])
    return keep.mean(1)


def ap50_on(dets, data, views, num_classes: int) -> tuple[float, int]:
    """AP50 (boxes the camera cuts ignored, as the protocol scores) over ``views``, and the
    number of boxes that count there."""
    truth = [data.truth(i) for i in views]
    found = [(dets[i]["boxes"], dets[i]["classes"], dets[i]["scores"]) for i in views]
    ignored = [data.ignored(i) for i in views]
    return coco_ap(truth, found, num_classes, ignored)["AP50"], int(sum((~i).sum() for i in ignored))


def miou_on(pixels: np.ndarray, ds, views) -> float:
    """mIoU over ``views`` of a segmentation split from its pixel predictions ``[S, H, W]``:
    one confusion matrix summed over those views, as the protocol scores a whole test."""
    conf = sum(confusion_matrix(pixels[i], ds.label_image[i].numpy(), len(SEMANTIC_CLASSES))
               for i in views)
    return scores(conf)["mIoU"]


def detection_scores(model, ds):
    """``up -> (views -> (AP50, counted boxes))`` for a detector on the split ``ds``."""
    data = det.DetectionSet.spherical(ds)

    def with_up(up):
        dets = det.predict(model, data, progress=False, up=up)
        return lambda views: ap50_on(dets, data, views, model.num_classes)
    return with_up


def segmentation_scores(model, ds):
    """``up -> (views -> (mIoU, None))`` for a segmenter on the split ``ds``."""
    def with_up(up):
        pixels = seg_eval.predict(model, ds, progress=False, up=up)[0]
        return lambda views: (miou_on(pixels, ds, views), None)
    return with_up


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoint", help="a spherical checkpoint of 'usf-graph train seg|det'")
    p.add_argument("--root", default="data/rooms")
    p.add_argument("--test", default="d", choices=["a", "b", "c", "d"])
    p.add_argument("--seed", type=int, default=None,
                   help="the protocol's seed, its rooms (default: the checkpoint's own)")
    p.add_argument("--num-test", type=int, default=50)
    args = p.parse_args(argv)
    ckpt = load_protocol_model(args.checkpoint)
    model = ckpt.model.eval()
    if getattr(model, "gravity", None) is None:
        raise SystemExit(f"{args.checkpoint} has no up estimate (a planar model?)")
    seed = ckpt.rooms_seed(args.seed)
    if ckpt.task == "det":
        ds = det.protocol_sets(args.root, ckpt.size, num_train=0, num_test=args.num_test,
                               seed=seed, progress=False, materials=ckpt.materials)[args.test]
    else:
        ds = seg.protocol_sets(args.root, ckpt.size, ckpt.config.get("level", 5), num_train=0,
                               num_test=args.num_test, seed=seed, tests=(args.test,),
                               progress=False, materials=ckpt.materials)[args.test]
    share = floor_and_ceiling(ds)
    err = up_errors(model.gravity, ds.x, ds.mask[0], views_up(ds))[0].numpy()
    res = {"bins": []}
    print(f"({args.test}) views by their share of floor and ceiling pixels, and the up "
          f"estimate's errors over {GROSS_DEGREES:.0f} degrees:")
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        sel = (share >= lo) & (share < hi)
        gross, flipped = int((err[sel] > GROSS_DEGREES).sum()), int((err[sel] > FLIPPED).sum())
        res["bins"].append({"share": [lo, min(hi, 1.0)], "views": int(sel.sum()),
                            "gross": gross, "upside_down": flipped})
        print(f"  [{lo:.2f}, {min(hi, 1.0):.2f}): {sel.sum():3d} views, {gross:3d} of them over "
              f"({flipped} over {FLIPPED:.0f}: upside down)")
    wall = share < WALL
    parts = {"wall close-ups": np.flatnonzero(wall), "the rest": np.flatnonzero(~wall),
             "all": np.arange(len(ds))}
    parts = {k: v for k, v in parts.items() if len(v)}  # a test may have no wall close-ups
    metric, scored = ("AP50", detection_scores) if ckpt.task == "det" else ("mIoU", segmentation_scores)
    score_views = scored(model, ds)
    for name, up in (("estimate", None), ("true up", views_up(ds))):
        on = score_views(up)
        for part, views in parts.items():
            value, boxes = on(views)
            res.setdefault(metric, {}).setdefault(name, {})[part] = value
            what = "pixels" if boxes is None else f"{boxes:4d} boxes"
            print(f"  {name:8s} {part:15s} {len(views):3d} views, {what}: {metric} {100 * value:.2f}")
    return res


if __name__ == "__main__":
    main()
