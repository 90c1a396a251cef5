"""Training and loading a :class:`~usf_graph.models.SignCheck`, the small network that says
whether an up estimate points up or down (``docs/up_estimate.md``)."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from tqdm.auto import tqdm

from .fov import RandomFields
from .gravity import views_up


def jittered(g: torch.Tensor, degrees: float, gen: torch.Generator) -> torch.Tensor:
    """``g [B, 3]`` (unit) turned by a uniform angle of up to ``degrees`` about random axes
    orthogonal to it, drawn from ``gen``."""
    v = torch.randn(g.shape, generator=gen, dtype=g.dtype)
    v = F.normalize(v - (v * g).sum(-1, keepdim=True) * g, dim=-1)
    t = torch.deg2rad(torch.rand(len(g), 1, generator=gen, dtype=g.dtype) * degrees)
    return torch.cos(t) * g + torch.sin(t) * v


def pretrain_sign(check, train, epochs: int = 4, cut_epochs: int = 4, share: float = 0.7,
                  seed: int = 0, batch_size: int = 8, jitter: float = 8.0,
                  lr: tuple[float, float] = (3e-3, 1e-3), progress: bool = True):
    """Trains a :class:`~usf_graph.models.SignCheck` on ``train`` (views of known gravity
    :func:`views_up`, on the check's grid) by ``softplus(s(-g) - s(g))``, with g turned by
    up to ``jitter`` degrees (an estimate is never exact). First ``epochs`` on whole views
    at ``lr[0]``, then ``cut_epochs`` at ``lr[1]`` with a share ``share`` of the batches
    seen through one random field of view (:class:`~usf_graph.train.fov.RandomFields`)
    and the normalizations frozen: training them on cut batches breaks the check on whole
    views (``docs/seg_det_log.md``, session 27). ``seed``: the batches' order, the fields
    and the jitter (seed the check's initialization yourself). Returns the check in
    evaluation mode."""
    from .engine import freeze_norms

    x_all, g_all = train.x, views_up(train).double()
    if x_all.shape[1] != len(check.area):
        raise ValueError(f"the views have {x_all.shape[1]} points, the sign check reads "
                         f"{len(check.area)}: build it for the views' grid")
    gen = torch.Generator().manual_seed(seed)
    params = [p for p in check.parameters() if p.requires_grad]
    for n_epochs, cut, rate in ((epochs, 0.0, lr[0]), (cut_epochs, share, lr[1])):
        if not n_epochs:
            continue
        fields = RandomFields(train.grid.pos, cut, seed)
        opt = torch.optim.Adam(params, lr=rate)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(
            opt, n_epochs * math.ceil(len(x_all) / batch_size))
        for _ in tqdm(range(n_epochs), desc=f"sign check, {cut:.0%} cut", disable=not progress):
            check.train()
            if cut:
                freeze_norms(check)
            order = torch.randperm(len(x_all), generator=gen)
            for i in range(0, len(x_all), batch_size):
                idx = order[i:i + batch_size]
                x, g = x_all[idx].float(), jittered(g_all[idx], jitter, gen).float()
                mask = fields()
                loss = F.softplus(check.score(x, mask, -g) - check.score(x, mask, g)).mean()
                if not torch.isfinite(loss):
                    raise FloatingPointError("the sign check's loss is not finite: check the "
                                             "views for NaN")
                opt.zero_grad()
                loss.backward()
                opt.step()
                sched.step()
    return check.eval()


def load_sign_check(path):
    """A :class:`~usf_graph.models.SignCheck` saved with
    :func:`~usf_graph.train.engine.save_checkpoint` (config ``{"model": "sign_check",
    ...}``, as ``examples/up_sign.py --save`` writes it), in evaluation mode."""
    from ..models import SignCheck
    from .engine import load_checkpoint

    blob = load_checkpoint(path)
    cfg = dict(blob.get("config") or {})
    if cfg.pop("model", None) != "sign_check":
        raise ValueError(f"{path} is not a sign check (examples/up_sign.py --save writes one)")
    check = SignCheck.from_config(cfg)
    check.load_state_dict(blob["state_dict"])
    return check.eval()


__all__ = ["jittered", "pretrain_sign", "load_sign_check"]
