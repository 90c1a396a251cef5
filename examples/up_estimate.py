"""How well does the equivariant up estimate work on its own?

Trains the segmenters' :class:`~usf_graph.models.UpNet` alone, as the rooms protocol does
(:func:`~usf_graph.train.gravity.pretrain_up`, on upright panoramas, icosahedral:5), and
reports its error on the protocol's test views: (a) new rooms' panoramas, (c) the 190-degree
fisheye and (d) the 90-degree pinhole (zero-shot, on what each lens sees), after the
polish (:class:`~usf_graph.models.UpPolish`), with the head's own median beside it.

    .venv/bin/python examples/up_estimate.py [--num-train 400] [--epochs 24] [--no-edge-votes] [--caps 0.5]
        [--cap-degrees 45 100] [--extra 1600]

About 75 s for 400 rooms x 24 epochs on 2 cores, after the rooms are rendered (``data/rooms``).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from torch import nn

from usf_graph.geometry import geodesic_distance
from usf_graph.models import UpNet
from usf_graph.train.gravity import pretrain_up, up_report, up_views, views_up
from usf_graph.train.seg import protocol_sets


@torch.no_grad()
def up_errors(up_net: nn.Module, ds, key: str = "up") -> np.ndarray:
    """Angles (degrees) between the estimated up and +z on the upright views of ``ds``
    (``key="up_head"``: the head's estimate, before the polish)."""
    x, mask = ds.x.float(), ds.mask[0]
    mask = None if mask.all() else mask
    up = torch.cat([up_net(x[i:i + 8], mask)[key] for i in range(0, len(x), 8)])
    z = torch.tensor([0.0, 0.0, 1.0]).expand_as(up)
    return torch.rad2deg(geodesic_distance(up, z)).numpy()


def summary(err: np.ndarray) -> dict:
    return {"median_deg": float(np.median(err)), "p90_deg": float(np.percentile(err, 90)),
            "over_60deg": int((err > 60).sum()), "views": len(err)}


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--root", default="data/rooms")
    p.add_argument("--num-train", type=int, default=400)
    p.add_argument("--num-test", type=int, default=50)
    p.add_argument("--epochs", type=int, default=24)
    p.add_argument("--size", type=int, default=96, help="panorama height")
    p.add_argument("--level", type=int, default=5)
    p.add_argument("--no-edge-votes", action="store_true", help="content scores only")
    p.add_argument("--caps", type=float, default=0.0,
                   help="share of training batches seen through a random cap only")
    p.add_argument("--cap-degrees", type=float, nargs=2, default=(45.0, 100.0),
                   metavar=("MIN", "MAX"), help="the random caps' angular radius range")
    p.add_argument("--extra", type=int, default=0,
                   help="cheap upright panoramas of other rooms added to training (RoomsGravity)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-progress", action="store_true")
    a = p.parse_args(argv)
    sets = protocol_sets(a.root, a.size, a.level, a.num_train, a.num_test, tests=("a", "c", "d"),
                         progress=not a.no_progress)
    torch.manual_seed(a.seed)
    holder = nn.Module()
    holder.gravity = UpNet(3, a.level, edge_votes=not a.no_edge_votes)
    t = time.time()
    pretrain_up(holder, sets["train"], a.epochs, seed=a.seed, progress=not a.no_progress,
                caps=a.caps, cap_degrees=a.cap_degrees,
                extra=up_views(a.root, a.extra, f"icosahedral:{a.level}", not a.no_progress))
    res = {"seconds": round(time.time() - t, 1)}
    up_net = holder.gravity.eval()
    for k in ("train", "a", "c", "d"):
        res[k] = summary(up_errors(up_net, sets[k]))
        r = res[k]
        r["head_median_deg"] = float(np.median(up_errors(up_net, sets[k], "up_head")))
        rep = up_report(up_net, sets[k].x, sets[k].mask[0], views_up(sets[k]))
        r.update(unsure=rep["unsure"], over_60deg_unsure=rep["gross_unsure"])
        print(f"({k}) up error median {r['median_deg']:.1f} deg (the head's {r['head_median_deg']:.1f} "
              f"before the polish), 90th percentile {r['p90_deg']:.1f} deg, {r['over_60deg']} of "
              f"{r['views']} views over 60 deg ({r['over_60deg_unsure']} of them flagged unsure, "
              f"{r['unsure']} in all)", flush=True)
    return res


if __name__ == "__main__":
    main()
