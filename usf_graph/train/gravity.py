"""How dense spherical models with an up estimate (``gravity=True``) are trained: the
network reads the heights along the views' known gravity, slightly jittered, while its
:class:`~usf_graph.models.UpNet` learns to estimate that gravity from the image, either
in the same steps or beforehand and alone (:func:`pretrain_up`, then frozen); and how a
test split's up is read (:func:`split_up`: the estimate, its pick among the straight
lines' axes, or the views' known gravity) and reported (:func:`up_report`). The sign
check: :mod:`usf_graph.train.sign`."""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import torch
from torch_geometric.data import Data, Dataset

from ..geometry import geodesic_distance
from ..models.gravity import UNSURE_MARGIN, pick_axis
from ..nn.batching import to_static
from .devices import is_planar, model_device
from .engine import fit
from .fov import random_cap

#: Weight of the up estimate's loss (:meth:`GravityHead.loss`) in a training step.
UP_WEIGHT = 0.5
#: Angular radius range of the random caps the up estimate is trained through.
UP_CAP_DEGREES = (40.0, 100.0)
#: Noise (per axis) on the true up that the network reads in training, so that it learns
#: to tolerate the estimate's error at test time.
UP_JITTER = 0.05
#: An up estimate farther than this (degrees) from the true up is a gross error in reports:
#: the wrong one of a room's vanishing directions, not an imprecise right one.
GROSS_DEGREES = 60.0


def known_up(batch, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(g, jittered g)``, each ``[B, 3]`` in the dtype and on the device of the batch's
    signals ``x [B, ...]``: the batch's ``up`` when it has one, else +z (gravity-aligned
    views)."""
    g = getattr(batch, "up", None)
    g = torch.tensor([0.0, 0.0, 1.0]).expand(len(x), 3) if g is None else g.view(-1, 3)
    g = g.to(x.device, x.dtype)
    # drawn by the CPU's generator wherever x is, so a GPU run jitters as the CPU's does
    return g, g + UP_JITTER * torch.randn(g.shape, dtype=g.dtype).to(g.device)


def views_up(ds) -> torch.Tensor:
    """The known gravity of every view of ``ds``, ``[S, 3]`` (its ``gravity``: an IMU's
    reading, e.g. :attr:`RoomsSegmentation.gravity <usf_graph.datasets.RoomsSegmentation>`)."""
    g = getattr(ds, "gravity", None)
    if g is None:
        raise ValueError(f"{type(ds).__name__} does not know its views' gravity; a known up needs "
                         "the protocol's rooms (RoomsSegmentation / RoomsDetection)")
    return g


def given_up(up: torch.Tensor | None, x: torch.Tensor, start: int = 0) -> dict:
    """Keyword arguments that hand known gravity to the batch ``x``: ``up [3]`` for every
    sample, or ``up [S, 3]`` for a whole split whose samples ``start .. start + len(x)`` are
    in the batch (``{}`` when ``up`` is None: the model reads its estimate)."""
    if up is None:
        return {}
    up = up.to(x.device, x.dtype)
    return {"up": up[start:start + len(x)] if up.dim() == 2 else up.expand(len(x), 3)}


@torch.no_grad()
def estimate_up(gravity, x: torch.Tensor, mask: torch.Tensor | None,
                batch_size: int = 16, axes: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """An up estimate (an :class:`~usf_graph.models.UpNet`, e.g. ``model.gravity``, run
    polished as at test time, on its own device) on views ``x [S, N, C]`` (``mask [N]`` or
    ``None``) -> ``(up [S, 3], margin [S])`` on the CPU. ``axes [S, 3, 3]`` (NaN for a
    view without; :func:`lines_axes`): each view's up is instead the head's pick among
    them (:func:`~usf_graph.models.gravity.pick_axis`)."""
    if mask is not None and mask.all():
        mask = None  # every point seen: the estimate runs unmasked, as the models run it
    if axes is not None and axes.shape != (len(x), 3, 3):
        raise ValueError(f"axes must be [{len(x)}, 3, 3], one set per view, got {tuple(axes.shape)}")
    dev = model_device(gravity)
    mask = None if mask is None else mask.to(dev)
    was_training = gravity.training
    gravity.eval()  # the polished estimate, as at test time
    ups, margins = [], []
    try:
        for s in range(0, len(x), batch_size):
            out = gravity(x[s:s + batch_size].to(dev).float(), mask)
            up = out["up"]
            if axes is not None:
                a = axes[s:s + batch_size].to(dev, up.dtype)
                has = torch.isfinite(a).all(-1).all(-1)
                pick = pick_axis(out["logits"], gravity.head.candidates.to(up.dtype), a.nan_to_num())
                up = torch.where(has[:, None], pick, up)
            ups.append(up.cpu())
            margins.append(out["margin"].cpu())
    finally:
        gravity.train(was_training)
    return torch.cat(ups), torch.cat(margins)


def lines_axes(ds) -> torch.Tensor:
    """The Manhattan axes of the straight lines of each image of a split (``ds.image [S, H,
    W, C]`` taken by ``ds.camera``, any model; :func:`~usf_graph.frontend.lines.image_axes`)
    -> ``[S, 3, 3]``, NaN for an image with too few lines."""
    from ..frontend.lines import image_axes

    axes = image_axes(ds.image.numpy(), ds.camera)
    nan = torch.full((3, 3), float("nan"), dtype=torch.float64)
    return torch.stack([nan if a is None else torch.as_tensor(a) for a in axes]) if axes else \
        torch.zeros(0, 3, 3, dtype=torch.float64)


def split_mask(ds) -> torch.Tensor | None:
    """The field of view a split's views share, ``[N]`` or ``None``; a split whose views
    see different parts of the sphere (several cameras, e.g. WoodScape's) is refused:
    score it with :func:`~usf_graph.train.real.evaluate_fields`, which batches by field."""
    mask = getattr(ds, "mask", None)
    if mask is None or mask.dim() == 1:
        return mask
    if not bool((mask == mask[0]).all()):
        raise ValueError(f"the views of this {type(ds).__name__} split have different fields of "
                         "view (several cameras); evaluate it with "
                         "usf_graph.train.real.evaluate_fields, which batches by field of view")
    return mask[0]


def lines_up(gravity, ds) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The up estimate ``gravity`` picking among the straight-line axes of each image of
    the split ``ds`` (:func:`estimate_up` with :func:`lines_axes`) -> ``(up [S, 3], axes [S,
    3, 3])``; ``None`` when the split has no one camera (``ds.camera``) to read lines
    through."""
    if getattr(ds, "camera", None) is None:
        return None
    up, _, axes = _split_estimate(gravity, ds, up_lines=True)
    return up, axes


def _split_estimate(gravity, ds, up_lines: bool = False, batch_size: int = 16):
    """The estimate ``gravity`` on every view of the split ``ds`` -> ``(up [S, 3], margin
    [S], axes [S, 3, 3] or None)``; with ``up_lines`` and one camera, its pick among each
    image's straight-line axes (:func:`lines_axes`)."""
    axes = lines_axes(ds) if up_lines and getattr(ds, "camera", None) is not None else None
    return (*estimate_up(gravity, ds.x, split_mask(ds), batch_size, axes), axes)


def check_up_choice(known_up: bool, up_lines: bool) -> None:
    """Refuses a known up together with the straight lines' pick: each replaces the estimate."""
    if known_up and up_lines:
        raise ValueError("a known up (--known-up) and the straight lines' pick (--up-lines) "
                         "exclude each other: give one")


def require_up_estimate(model, what: str) -> None:
    """Refuses ``what`` (an option that reads the model's up estimate, e.g. the straight
    lines' pick) for a model without one."""
    if getattr(model, "gravity", None) is None:
        raise ValueError(f"{what} needs a spherical model with an up estimate (gravity=True); "
                         "this model has none")


def _degrees_off(up: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    return torch.rad2deg(geodesic_distance(up.double(), g.double()))


def up_summary(up: torch.Tensor, margin: torch.Tensor, g: torch.Tensor,
               axes: torch.Tensor | None = None) -> dict:
    """How estimates ``up [S, 3]`` with their ``margin [S]`` fared against known gravity
    ``g [S, 3]``: the median error in degrees, the number of ``gross`` errors (over
    :data:`GROSS_DEGREES`), of views it is ``unsure`` of (``margin`` below
    :data:`~usf_graph.models.gravity.UNSURE_MARGIN`) and of gross errors among those;
    with ``axes`` (:func:`lines_axes`), the number of views that had ``lines``."""
    err = _degrees_off(up, g)
    gross, unsure = err > GROSS_DEGREES, margin < UNSURE_MARGIN
    r = {"views": len(err), "median_err_deg": round(float(err.quantile(0.5)), 2),
         "gross": int(gross.sum()), "unsure": int(unsure.sum()),
         "gross_unsure": int((gross & unsure).sum())}
    if axes is not None:  # the views whose up was picked among their straight lines' axes
        r["lines"] = int(torch.isfinite(axes).all(-1).all(-1).sum())
    return r


class SplitUp(NamedTuple):
    """What a model reads on a test split (:func:`split_up`): ``up [S, 3]`` to hand to
    ``predict`` (``None``: a model without an up estimate, or a planar one), the straight
    lines' ``axes [S, 3, 3]`` it picked among (or ``None``), and the model's own
    ``estimate [S, 3]`` with its ``margin [S]`` (``None`` without an estimate), computed
    once for both the prediction and :meth:`report`."""

    up: torch.Tensor | None
    axes: torch.Tensor | None
    estimate: torch.Tensor | None
    margin: torch.Tensor | None

    def report(self, g: torch.Tensor) -> dict | None:
        """:func:`up_summary` of the estimate against known gravity ``g [S, 3]``;
        ``None`` without an estimate."""
        return None if self.estimate is None else up_summary(self.estimate, self.margin, g, self.axes)


def split_up(model, ds, known_up: bool = False, up_lines: bool = False,
             batch_size: int = 16) -> SplitUp:
    """The up a model reads on a test split ``ds`` (``ds.x [S, N, C]``, ``ds.mask``),
    with its estimate run once (:func:`estimate_up`, ``batch_size`` views at a time, as the
    model's prediction batches them so the numbers are the model's own): the views'
    gravity with ``known_up`` (:func:`views_up`), else the estimate, which with
    ``up_lines`` picks among each image's straight-line axes where the split has one
    camera, of any lens (:func:`lines_axes`; a split without one, a rig's, keeps the plain
    estimate, and ``axes`` is ``None``).
    A planar model reads no up."""
    check_up_choice(known_up, up_lines)
    if is_planar(model):
        return SplitUp(None, None, None, None)
    if up_lines:
        require_up_estimate(model, "the straight lines' pick (up_lines)")
    gravity, est, margin, axes = getattr(model, "gravity", None), None, None, None
    if gravity is not None:
        est, margin, axes = _split_estimate(gravity, ds, up_lines, batch_size)
    return SplitUp(views_up(ds) if known_up else est, axes, est, margin)


def up_errors(gravity, x: torch.Tensor, mask: torch.Tensor | None, g: torch.Tensor,
              batch_size: int = 16, axes: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Per view, the error in degrees of :func:`estimate_up` (with ``axes``: its pick among
    them) on views of known gravity ``g [S, 3]``, and its ``margin`` -> ``(error [S],
    margin [S])``."""
    up, margin = estimate_up(gravity, x, mask, batch_size, axes)
    return _degrees_off(up, g), margin


def up_report(gravity, x: torch.Tensor, mask: torch.Tensor | None, g: torch.Tensor,
              batch_size: int = 16, axes: torch.Tensor | None = None) -> dict:
    """:func:`up_summary` of an up estimate run on views of known gravity (:func:`up_errors`'s
    arguments)."""
    return up_summary(*estimate_up(gravity, x, mask, batch_size, axes), g, axes)


def format_up_report(r: dict) -> str:
    """One line of :func:`up_report`'s numbers."""
    lines = f"; picked among straight-line axes on {r['lines']} views" if "lines" in r else ""
    return (f"up estimate: median error {r['median_err_deg']:.1f} deg, {r['gross']} of {r['views']} "
            f"views over {GROSS_DEGREES:.0f} deg ({r['gross_unsure']} of them flagged unsure); "
            f"{r['unsure']} flagged unsure in all{lines}")


def up_loss(head, grav: dict, g: torch.Tensor, stats: dict, sign_weight: float = 0.0) -> torch.Tensor:
    """``UP_WEIGHT`` times the up estimate's loss (``head``: its
    :class:`~usf_graph.models.GravityHead`; ``sign_weight``: its
    :meth:`~usf_graph.models.GravityHead.loss`'s); records its mean error (degrees)."""
    stats["up_err_deg"] = float(torch.rad2deg(geodesic_distance(grav["up"].detach(), g)).mean())
    return UP_WEIGHT * head.loss(grav, g, sign_weight)


def trains_up(net) -> bool:
    """Whether ``net`` (or its DDP wrapper) has an up estimate that is still being trained."""
    return bool(getattr(getattr(net, "module", net), "trains_up", False))


def up_step(model, batch, caps: float = 0.0, cap_degrees: tuple[float, float] = UP_CAP_DEGREES,
            sign_weight: float = 0.0):
    """The engine's step for an :class:`~usf_graph.models.UpNet` alone, on PyG batches of
    views of known gravity (:func:`known_up`): :meth:`GravityHead.loss` (with its
    ``sign_weight``). With probability ``caps`` the batch is seen through a
    :func:`random_cap` only (a smaller lens), of an angular radius drawn from
    ``cap_degrees``."""
    B = batch.num_graphs
    x, _ = to_static(batch.x, batch.x.shape[0] // B, batch.batch, "up batch")
    seen = getattr(batch, "mask", None)  # panoramas may come without one
    if seen is not None and not (seen.view(B, -1) == seen.view(B, -1)[0]).all():
        raise ValueError("the views of an up batch have different fields of view; batch one "
                         "camera (groups=field_groups(dataset.mask))")
    mask = torch.ones(x.shape[1], dtype=torch.bool, device=x.device) if seen is None else \
        seen.view(B, -1)[0]
    if caps and float(torch.rand(())) < caps:
        both = mask & random_cap(batch.pos[: x.shape[1]], *cap_degrees)
        mask = both if both.any() else mask
    g, _ = known_up(batch, x)
    out = model(x, None if mask.all() else mask)
    stats = {}
    loss = up_loss(getattr(model, "module", model).head, out, g, stats, sign_weight)
    return loss, stats, B


class UpViews(Dataset):
    """The views of several PyG datasets of known gravity, each with only what
    :func:`up_step` reads (``x``, ``pos``, ``mask``, ``up``), so that datasets with other
    fields (labels, boxes) batch together."""

    def __init__(self, *datasets):
        self.parts = [d for d in datasets if d is not None]
        self.ends = torch.tensor([len(d) for d in self.parts]).cumsum(0)
        super().__init__()

    def len(self) -> int:
        return int(self.ends[-1]) if len(self.ends) else 0

    def get(self, idx: int) -> Data:
        k = int(torch.searchsorted(self.ends, idx, right=True))
        d = self.parts[k][idx - (int(self.ends[k - 1]) if k else 0)]
        up = getattr(d, "up", None)
        return Data(x=d.x, pos=d.pos, mask=d.mask,
                    up=torch.tensor([[0.0, 0.0, 1.0]]) if up is None else up.view(1, 3))


def check_extra_rooms(seed: int, up_extra: int) -> None:
    """Refuses a rooms protocol of ``seed`` whose test rooms would be the up estimate's
    extra panoramas (:class:`~usf_graph.datasets.RoomsGravity`'s rooms)."""
    from ..datasets.rooms import GRAVITY_SEED, split_seed

    if up_extra and split_seed("test", seed) == GRAVITY_SEED:
        raise ValueError(f"the test rooms of seed {seed} are the up estimate's extra panoramas "
                         f"(the rooms of seed {GRAVITY_SEED}); pick another seed")


def up_views(root, num: int, grid="icosahedral:5", progress: bool = True,
             materials: str = "random"):
    """``num`` cheap upright panoramas on ``grid`` (:class:`~usf_graph.datasets.RoomsGravity`,
    rendered once under ``root``) for the protocols' up estimate, or ``None`` for 0."""
    if not num:
        return None
    from ..datasets import RoomsGravity

    return RoomsGravity(root, num, grid=grid, progress=progress, materials=materials)


def pretrain_up(net, train, epochs: int, batch_size: int = 8, lr: float = 3e-3, seed: int = 0,
                progress: bool = True, log_dir=None, caps: float = 0.0,
                cap_degrees: tuple[float, float] = UP_CAP_DEGREES, extra=None,
                sign_weight: float = 0.0, resume: bool = False, groups=None) -> None:
    """Trains ``net.gravity`` alone on ``train`` (views of known gravity), and ``extra``
    views when given (e.g. :class:`~usf_graph.datasets.RoomsGravity`), for ``epochs``,
    then freezes it: the segmenter's own training then reads the known gravity and never
    runs it. The up estimate is small (tens of ms a step), so it can see many views at
    little cost, which it needs (README). ``caps``, ``cap_degrees`` and ``sign_weight``:
    see :func:`up_step`; ``resume``, ``groups`` (``train``'s fields of view; no
    ``extra`` then): as :func:`~usf_graph.train.engine.fit`'s."""
    if extra is not None:
        if groups is not None:
            raise ValueError("groups are the training set's; extra views cannot join them")
        train = UpViews(train, extra)
    fit(net.gravity, train, None, epochs=epochs, batch_size=batch_size, lr=lr, seed=seed,
        log_dir=log_dir, progress=progress, name="up estimate", resume=resume, groups=groups,
        step=partial(up_step, caps=caps, cap_degrees=tuple(cap_degrees), sign_weight=sign_weight))
    net.gravity.requires_grad_(False)


__all__ = ["UP_WEIGHT", "UP_JITTER", "GROSS_DEGREES", "estimate_up", "lines_axes", "lines_up", "split_mask", "check_up_choice", "require_up_estimate", "split_up", "SplitUp", "up_summary", "up_errors", "up_report", "format_up_report", "known_up", "views_up", "given_up", "up_loss", "up_step", "pretrain_up", "trains_up", "UpViews", "up_views",
           "UP_CAP_DEGREES"]
