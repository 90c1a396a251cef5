"""A learned sign check for a segmentation checkpoint's up estimate (session 27's lead).

With the level prior (``--level-prior``), what the up estimate still gets wrong through the
fisheye is mostly the sign. This trains a sign check and asks it on the protocol's tests:
a :class:`~usf_graph.models.SignCheck` (an upright ``SphericalUNet`` with one output
channel, the protocol's U-Net configuration, trained by
:func:`~usf_graph.train.sign.pretrain_sign`) reads the image with heights and ``UpJet`` features along a candidate
up u. Its score s(u) is the area-weighted mean output over the visible points, trained by
``softplus(s(-g) - s(g))`` on the training views' known gravity g, jittered. It trains
first on whole panoramas, then with a share of the batches through random fields of view
and the normalizations frozen (training them on cut batches breaks it at test). At test
the estimate u is flipped where s(-u) > s(u). Everything depends on u only through
heights and derivatives along it, so the check rotates with the input.

    .venv/bin/python examples/up_sign.py runs/seg_seed1/spherical_deeplab.pt --seed 1 --level-prior 10 \
        --save runs/seg_seed1/sign_check.pt

About 12 minutes on 2 cores once the protocol's rooms are rendered (``data/rooms``).
Prints, per test, the estimate's gross errors (over 60 degrees) and the mIoU on pixels
before and after the check (docs/seg_det_log.md, session 27). Here the check is asked on
every test; attached to a model (``set_sign_check``, or ``usf-graph eval seg|det
--sign-check`` with the ``--save``d file) it is asked only on wide fields of view.
"""

from __future__ import annotations

import argparse

import torch

from usf_graph.geometry import geodesic_distance
from usf_graph.models import SignCheck, set_level_prior
from usf_graph.train import save_checkpoint, seg, seg_eval, seg_metrics
from usf_graph.train.checkpoints import load_protocol_model
from usf_graph.train.engine import seed_everything
from usf_graph.train.gravity import GROSS_DEGREES, views_up
from usf_graph.train.sign import pretrain_sign


@torch.no_grad()
def checked(sign, model, ds, batch=16):
    """The estimate's ups ``[S, 3]`` for ``ds`` and the same after the sign check (asked
    whatever the field of view, to show where it helps and where it harms)."""
    mask = None if ds.mask[0].all() else ds.mask[0]
    ups, out = [], []
    for s in range(0, len(ds), batch):
        x = ds.x[s:s + batch].float()
        u = model.gravity(x, mask)["up"]
        ups.append(u)
        out.append(sign.correct(x, mask, u))
    return torch.cat(ups), torch.cat(out)


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoint", help="a spherical checkpoint of 'usf-graph train seg'")
    p.add_argument("--root", default="data/rooms")
    p.add_argument("--seed", type=int, default=None,
                   help="the protocol's seed, its rooms (default: the checkpoint's own)")
    p.add_argument("--num-train", type=int, default=400)
    p.add_argument("--num-test", type=int, default=50)
    p.add_argument("--epochs", type=int, default=4, help="on whole panoramas")
    p.add_argument("--cut-epochs", type=int, default=4, help="then through random fields of view")
    p.add_argument("--share", type=float, default=0.7, help="of the batches cut then")
    p.add_argument("--level-prior", type=float, default=10.0, help="the estimate's (0: off)")
    p.add_argument("--save", default=None, help="write the trained check here (a checkpoint "
                   "for 'usf-graph eval seg|det --sign-check')")
    p.add_argument("--no-progress", action="store_true")
    a = p.parse_args(argv)
    ckpt = load_protocol_model(a.checkpoint).require("seg", spherical=True)
    model, cfg, size = ckpt.model, ckpt.config, ckpt.size
    a.seed = ckpt.rooms_seed(a.seed)
    model.eval()
    set_level_prior(model, a.level_prior)
    sets = seg.protocol_sets(a.root, size, cfg["level"], a.num_train, a.num_test, a.seed,
                             tests=("a", "c", "d"), progress=not a.no_progress,
                             materials=ckpt.materials)
    seed_everything(a.seed)
    sign = pretrain_sign(SignCheck(cfg["level"]), sets["train"], a.epochs, a.cut_epochs, a.share,
                         a.seed, progress=not a.no_progress)
    res = {}
    for k in ("a", "c", "d"):
        ds, g = sets[k], views_up(sets[k]).double()
        up, fixed = checked(sign, model, ds)
        r = {"flipped": int((fixed != up).any(-1).sum())}
        for when, u in (("before", up), ("after", fixed)):
            err = torch.rad2deg(geodesic_distance(u.double(), g))
            pix, pts = seg_eval.predict(model, ds, progress=False, up=u)
            r[when] = {"gross": int((err > GROSS_DEGREES).sum()),
                       "mIoU": seg_metrics.score(pix, ds, pts)["mIoU"]}
        res[k] = r
        print(f"({k}) gross errors {r['before']['gross']} -> {r['after']['gross']} ({r['flipped']} "
              f"flipped), mIoU {100 * r['before']['mIoU']:.2f} -> {100 * r['after']['mIoU']:.2f}")
    if a.save:
        save_checkpoint(a.save, sign, {"model": "sign_check", **sign.config}, res)
        print(f"sign check: {a.save}")
    return res


if __name__ == "__main__":
    main()
