"""A learned sign check for a segmentation checkpoint's up estimate (session 27's lead).

With the level prior (``--level-prior``), what the up estimate still gets wrong through the
fisheye is mostly the sign. This trains a sign check and asks it on the protocol's tests:
an upright :class:`~usf_graph.models.SphericalUNet` (one output channel, the protocol's
U-Net configuration) reads the image with heights and ``UpJet`` features along a candidate
up u. Its score s(u) is the area-weighted mean output over the visible points, trained by
``softplus(s(-g) - s(g))`` on the training views' known gravity g, jittered. It trains
first on whole panoramas, then with a share of the batches through random fields of view
and the normalizations frozen (training them on cut batches breaks it at test). At test
the estimate u is flipped where s(-u) > s(u). Everything depends on u only through
heights and derivatives along it, so the check rotates with the input.

    .venv/bin/python examples/up_sign.py runs/seg_seed1/spherical_deeplab.pt --seed 1 --level-prior 10

About 12 minutes on 2 cores once the protocol's rooms are rendered (``data/rooms``).
Prints, per test, the estimate's gross errors (over 60 degrees) and the mIoU on pixels
before and after the check (docs/seg_det_log.md, session 27).
"""

from __future__ import annotations

import argparse
import math

import torch
import torch.nn.functional as F
from tqdm import tqdm

from usf_graph.geometry import geodesic_distance
from usf_graph.models import SphericalUNet, set_level_prior
from usf_graph.train import load_checkpoint, seg
from usf_graph.train.engine import freeze_norms, seed_everything
from usf_graph.train.fov import RandomFields
from usf_graph.train.gravity import GROSS_DEGREES, views_up


def upright_score(net, area, x, mask, up):
    """s(up) ``[B]``: ``net``'s area-weighted mean output over the visible points."""
    out = net(x, mask, up=up)[..., 0]
    w = area.to(out.dtype) * (1 if mask is None else mask.to(out.dtype))
    return (out * w).sum(-1) / w.sum()


def jittered(g, degrees, gen):
    """``g [B, 3]`` turned by a uniform angle up to ``degrees`` about random axes."""
    v = torch.randn(g.shape, generator=gen, dtype=g.dtype)
    v = F.normalize(v - (v * g).sum(-1, keepdim=True) * g, dim=-1)
    t = torch.deg2rad(torch.rand(len(g), 1, generator=gen, dtype=g.dtype) * degrees)
    return torch.cos(t) * g + torch.sin(t) * v


def train_sign(train, level, epochs, cut_epochs, share, seed, batch=8, jitter=8.0, progress=True):
    """The sign check, trained on ``train`` (views of known gravity)."""
    seed_everything(seed)
    net = SphericalUNet(num_classes=1, level=level, gravity=True, upright=True, pairs=0, up_fields=4)
    net.gravity.requires_grad_(False)  # never asked: the check is handed its candidate
    x_all, g_all = train.x, views_up(train).double()
    area, gen = train.grid.area.double(), torch.Generator().manual_seed(seed)
    for n_epochs, cut, lr in ((epochs, 0.0, 3e-3), (cut_epochs, share, 1e-3)):
        if not n_epochs:
            continue
        fields = RandomFields(train.grid.pos, cut, seed)
        opt = torch.optim.Adam([p for p in net.parameters() if p.requires_grad], lr=lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, n_epochs * math.ceil(len(x_all) / batch))
        for _ in tqdm(range(n_epochs), desc=f"sign check, {cut:.0%} cut", disable=not progress):
            net.train()
            if cut:
                freeze_norms(net)
            order = torch.randperm(len(x_all), generator=gen)
            for i in range(0, len(x_all), batch):
                idx = order[i:i + batch]
                x, g = x_all[idx].float(), jittered(g_all[idx], jitter, gen).float()
                mask = fields()
                right = upright_score(net, area, x, mask, g)
                loss = F.softplus(upright_score(net, area, x, mask, -g) - right).mean()
                opt.zero_grad()
                loss.backward()
                opt.step()
                sched.step()
    return net.eval()


@torch.no_grad()
def checked(sign, model, ds, batch=16):
    """The estimate's ups ``[S, 3]`` for ``ds`` and the same after the sign check."""
    mask = None if ds.mask[0].all() else ds.mask[0]
    area, ups, out = ds.grid.area.double(), [], []
    for s in range(0, len(ds), batch):
        x = ds.x[s:s + batch].float()
        u = model.gravity(x, mask)["up"]
        flip = upright_score(sign, area, x, mask, -u) > upright_score(sign, area, x, mask, u)
        ups.append(u)
        out.append(torch.where(flip[:, None], -u, u))
    return torch.cat(ups), torch.cat(out)


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoint", help="a spherical checkpoint of 'usf-graph train seg'")
    p.add_argument("--root", default="data/rooms")
    p.add_argument("--seed", type=int, default=0, help="the protocol's seed (its rooms)")
    p.add_argument("--num-train", type=int, default=400)
    p.add_argument("--num-test", type=int, default=50)
    p.add_argument("--epochs", type=int, default=4, help="on whole panoramas")
    p.add_argument("--cut-epochs", type=int, default=4, help="then through random fields of view")
    p.add_argument("--share", type=float, default=0.7, help="of the batches cut then")
    p.add_argument("--level-prior", type=float, default=10.0, help="the estimate's (0: off)")
    p.add_argument("--no-progress", action="store_true")
    a = p.parse_args(argv)
    blob = load_checkpoint(a.checkpoint)
    cfg = dict(blob["config"])
    name, size = cfg.pop("model", None), cfg.pop("size", 96)
    if name not in seg.MODELS or seg.MODELS[name] is seg.PlanarUNet:
        raise SystemExit(f"{a.checkpoint} is not a spherical checkpoint of 'usf-graph train seg'")
    model = seg.MODELS[name].from_config(cfg)
    model.load_state_dict(blob["state_dict"])
    model.eval()
    set_level_prior(model, a.level_prior)
    sets = seg.protocol_sets(a.root, size, cfg["level"], a.num_train, a.num_test, a.seed,
                             tests=("a", "c", "d"), progress=not a.no_progress)
    sign = train_sign(sets["train"], cfg["level"], a.epochs, a.cut_epochs, a.share, a.seed,
                      progress=not a.no_progress)
    res = {}
    for k in ("a", "c", "d"):
        ds, g = sets[k], views_up(sets[k]).double()
        up, fixed = checked(sign, model, ds)
        r = {"flipped": int((fixed != up).any(-1).sum())}
        for when, u in (("before", up), ("after", fixed)):
            err = torch.rad2deg(geodesic_distance(u.double(), g))
            pix, pts = seg.predict(model, ds, progress=False, up=u)
            r[when] = {"gross": int((err > GROSS_DEGREES).sum()),
                       "mIoU": seg.score(pix, ds, pts)["mIoU"]}
        res[k] = r
        print(f"({k}) gross errors {r['before']['gross']} -> {r['after']['gross']} ({r['flipped']} "
              f"flipped), mIoU {100 * r['before']['mIoU']:.2f} -> {100 * r['after']['mIoU']:.2f}")
    return res


if __name__ == "__main__":
    main()
