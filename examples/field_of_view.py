"""Does a zero-shot lens lose points to the lens, or to its narrower field of view?

Scores a rooms protocol checkpoint (``usf-graph train seg`` or ``train det``) on what the
90-degree pinhole (test d) or the 190-degree fisheye (test c) sees, from these inputs of the
same views:

1. the whole panorama (test a's input);
2. the panorama masked to the lens's field of view;
3. the lens's own image (the protocol's test);
4. the lens's image inside its field of view and the panorama outside it;
5. the lens's image with every point it does not see given the colour of the nearest point
   it sees, and no mask: an input that looks whole to a network trained on panoramas;
6. (with the estimated up) 5, with the up estimated from 3, the real pixels only.

If 2 and 3 agree, the lens itself costs nothing; 1 minus 2 is what the narrower field of
view costs, and 4 shows it comes back with the context. 5 and 6 are test-time fills of
the hidden part (session 39). Segmentation: mIoU area-weighted
over the grid points the lens sees. Detection: AP50 on the lens's boxes, counting only
detections whose centre it sees.

    .venv/bin/python examples/field_of_view.py runs/seg/spherical_deeplab.pt [--known-up] [--test d]
    .venv/bin/python examples/field_of_view.py runs/det/spherical.pt --known-up

About 1-2 minutes on 2 cores once the protocol's rooms are rendered (``data/rooms``).
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from scipy.spatial import cKDTree

from usf_graph.models.centernet import box_centres
from usf_graph.train import det, seg
from usf_graph.train.checkpoints import load_protocol_model
from usf_graph.train.gravity import estimate_up, given_up, views_up
from usf_graph.train.seg_metrics import confusion_matrix, scores


def _segmenter_score(net, sets, test, up):
    """The inputs' area-weighted mIoU on the points the lens sees."""
    a, lens = sets["a"], sets[test]
    seen = lens.mask[0]
    weight = (a.grid.area * seen).numpy()[None].repeat(len(a), 0)

    @torch.no_grad()
    def miou(x, mask, up=up):
        pred = torch.cat([net(x[s:s + 8].float(), mask, **given_up(up, x[s:s + 8], s)).argmax(-1)
                          for s in range(0, len(x), 8)])
        return scores(confusion_matrix(pred.numpy(), a.y.numpy(), len(seg.SEMANTIC_CLASSES),
                                       weight=weight))["mIoU"]

    return _inputs(a.x, lens.x, seen, miou, nearest_seen(a.grid.pos, seen), _lens_up(net, lens.x, seen, up))


def _detector_score(net, sets, test, up):
    """The inputs' AP50 on the lens's boxes (those it cuts ignored, as the protocol
    does), detections whose centre it sees."""
    a, lens = det.DetectionSet.spherical(sets["a"]), det.DetectionSet.spherical(sets[test])
    cam = sets[test].camera

    def ap50(x, mask, up=up):
        data = det.DetectionSet(x, lens.boxes, lens.box_class, lens.box_ptr, mask, lens.seen)
        found = det.predict(net, data, progress=False, up=up)
        for d in found:
            _, keep = cam.sees(box_centres(torch.as_tensor(d["boxes"]).double()).numpy())
            keep = np.asarray(keep, bool)
            d.update({k: d[k][keep] for k in ("boxes", "classes", "scores")})
        return det.score(found, data, net.num_classes)["AP50"]

    return _inputs(a.x, lens.x, lens.mask, ap50, nearest_seen(sets[test].grid.pos, lens.mask),
                   _lens_up(net, lens.x, lens.mask, up))


def nearest_seen(pos: torch.Tensor, seen: torch.Tensor) -> torch.Tensor:
    """For every grid point ``pos [N, 3]``, the index of the nearest point the lens sees
    (``seen [N]``; a seen point is its own): a table of the camera and the grid only."""
    ids = torch.nonzero(seen).flatten()
    _, k = cKDTree(pos[ids].numpy()).query(pos.numpy())
    return ids[torch.as_tensor(k)]


def _lens_up(net, x, seen, up):
    """The up estimated from the lens's masked image, where the up is not given."""
    return estimate_up(net.gravity, x, seen)[0] if up is None else None


def _inputs(pano, lens, seen, metric, nearest, lens_up=None) -> dict:
    both = pano.clone()
    both[:, seen] = lens[:, seen]
    filled = lens[:, nearest]
    res = {"panorama": metric(pano, None), "panorama masked to the lens": metric(pano, seen),
           "the lens's image": metric(lens, seen), "lens inside, panorama outside": metric(both, None),
           "the lens's image, the rest filled": metric(filled, None)}
    if lens_up is not None:
        res["filled, up from the lens's image"] = metric(filled, None, lens_up)
    return res


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint")
    p.add_argument("--test", default="d", choices=["c", "d"], help="d: pinhole 90, c: fisheye 190")
    p.add_argument("--known-up", action="store_true", help="read each view's true gravity")
    p.add_argument("--root", default="data/rooms")
    p.add_argument("--num-test", type=int, default=50)
    p.add_argument("--seed", type=int, default=None,
                   help="the rooms' seed (default: the checkpoint's own)")
    p.add_argument("--size", type=int, default=None,
                   help="panorama height (default: the checkpoint's, or det's 128)")
    args = p.parse_args(argv)
    ckpt = load_protocol_model(args.checkpoint).require(spherical=True)
    net, size, seed = ckpt.model, args.size or ckpt.size, ckpt.rooms_seed(args.seed)
    if ckpt.task == "seg":
        sets = seg.protocol_sets(args.root, size, ckpt.config.get("level", 5), num_train=0,
                                 num_test=args.num_test, seed=seed, tests=("a", args.test),
                                 progress=False, materials=ckpt.materials)
        score, unit = _segmenter_score, "mIoU (area-weighted)"
    else:
        sets = det.protocol_sets(args.root, size, num_train=0, num_test=args.num_test,
                                 seed=seed, progress=False, materials=ckpt.materials)
        score, unit = _detector_score, "AP50"
    net.eval()
    up = views_up(sets["a"]) if args.known_up else None
    res = score(net, sets, args.test, up)
    print(f"{unit} on what test ({args.test}) sees, {'true' if up is not None else 'estimated'} up:")
    for k, v in res.items():
        print(f"  {k:32s} {100 * v:6.2f}")
    return res


if __name__ == "__main__":
    main()
