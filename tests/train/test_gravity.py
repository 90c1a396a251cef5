"""Handing known gravity to a batch, and the up estimate's training views (train.gravity)."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from torch import nn
from torch_geometric.data import Data
from torch_geometric.loader import DataLoader

from usf_graph.grids import icosahedral
from usf_graph.models import UpNet
from usf_graph.train.gravity import UpViews, given_up, pretrain_up, views_up


def test_given_up_hands_one_or_each_views_gravity_to_a_batch():
    x = torch.zeros(2, 5, 3, dtype=torch.float64)
    assert given_up(None, x) == {}
    z = torch.tensor([0.0, 0.0, 1.0])
    one = given_up(z, x)["up"]
    assert one.shape == (2, 3) and one.dtype == torch.float64 and (one == z.double()).all()
    split = torch.arange(12.0).view(4, 3)  # one per view of a 4-view split
    assert torch.equal(given_up(split, x, 1)["up"], split[1:3].double())
    assert torch.equal(given_up(split, x[:1], 3)["up"], split[3:].double())


def test_views_up_needs_a_split_that_knows_its_gravity():
    class Views:
        gravity = torch.eye(3)

    assert torch.equal(views_up(Views()), torch.eye(3))
    with pytest.raises(ValueError, match="does not know its views' gravity"):
        views_up(object())


def _views(n, value, up=None, N=4):
    return [Data(x=torch.full((N, 3), value + i), pos=torch.zeros(N, 3), y=torch.zeros(N),
                 mask=torch.ones(N, dtype=torch.bool), **({} if up is None else {"up": up}))
            for i in range(n)]


def test_up_views_join_datasets_with_only_what_the_up_step_reads():
    east = torch.tensor([[1.0, 0.0, 0.0]])
    v = UpViews(_views(2, 0.0, east), None, _views(3, 10.0))
    assert len(v) == 5
    assert [float(v[i].x[0, 0]) for i in range(5)] == [0.0, 1.0, 10.0, 11.0, 12.0]
    assert set(v[0].keys()) == {"x", "pos", "mask", "up"}
    assert torch.equal(v[1].up, east) and torch.equal(v[4].up, torch.tensor([[0.0, 0.0, 1.0]]))
    batch = next(iter(DataLoader(v, batch_size=5)))
    assert torch.equal(batch.up, torch.cat([east, east] + [torch.tensor([[0.0, 0.0, 1.0]])] * 3))
    assert len(UpViews()) == 0


def test_pretrain_up_reads_the_extra_views():
    """A NaN in an extra view reaches the up estimate (its clear error), so the extra views
    are trained on, not ignored."""
    g = icosahedral(3)
    views = [Data(x=torch.rand(len(g.pos), 3), pos=g.pos.float(), mask=torch.ones(len(g.pos), dtype=torch.bool))
             for _ in range(2)]
    holder = nn.Module()
    holder.gravity = UpNet(3, 3)
    pretrain_up(holder, views[:1], epochs=1, batch_size=2, progress=False, extra=views[1:])
    assert not any(p.requires_grad for p in holder.gravity.parameters())
    holder.gravity = _RecordingUpNet(3, 3)  # no caps unless asked: whole views
    pretrain_up(holder, views, epochs=2, batch_size=1, progress=False)
    assert holder.gravity.masks == [None] * 4
    bad = Data(x=torch.full((len(g.pos), 3), float("nan")), pos=g.pos.float(), mask=views[0].mask)
    holder.gravity = UpNet(3, 3)
    with pytest.raises((ValueError, FloatingPointError), match="NaN|non-finite"):
        pretrain_up(holder, views[:1], epochs=1, batch_size=1, progress=False, extra=[bad])


class _FixedEstimate(nn.Module):
    """An up estimate that answers given directions and margins, in order, and records the
    masks it is given in ``masks``."""

    def __init__(self, up, margin):
        super().__init__()
        self.up, self.margin, self.seen, self.masks = up, margin, 0, []

    def forward(self, x, mask=None):
        self.masks.append(mask)
        s, self.seen = self.seen, self.seen + len(x)
        return {"up": self.up[s:self.seen], "margin": self.margin[s:self.seen]}


def test_up_report_counts_gross_errors_and_the_views_it_was_unsure_of():
    from usf_graph.models.gravity import UNSURE_MARGIN
    from usf_graph.train.gravity import format_up_report, up_report

    z, x_ax = torch.tensor([0.0, 0.0, 1.0]), torch.tensor([1.0, 0.0, 0.0])
    tilt = torch.tensor([0.0, 0.5 ** 0.5, 0.5 ** 0.5])  # 45 degrees: wrong, not gross
    up = torch.stack([z, z, tilt, x_ax, -z])
    margin = torch.tensor([5.0, 0.5, 3.0, 0.2, 2.0]) * UNSURE_MARGIN
    r = up_report(_FixedEstimate(up, margin), torch.zeros(5, 7, 3), None, z.expand(5, 3),
                  batch_size=2)
    assert r == {"views": 5, "median_err_deg": 45.0, "gross": 2, "unsure": 2, "gross_unsure": 1}
    # it scores the estimate in evaluation mode and leaves a training module training
    net = UpNet(3, 3, channels=(4, 4)).double()
    x = torch.rand(2, len(icosahedral(3)), 3, dtype=torch.float64)
    r2 = up_report(net, x, None, torch.tensor([[0.0, 0.0, 1.0]]).expand(2, 3))
    assert net.training and r2["views"] == 2
    want = np.median(np.degrees(np.arccos(np.clip(net.eval()(x)["up"][:, 2].numpy(), -1, 1))))
    assert r2["median_err_deg"] == pytest.approx(want, abs=0.01)
    # a split's all-visible mask is the unmasked estimate; a partial one reaches the network
    full = torch.ones(x.shape[1], dtype=torch.bool)
    assert up_report(net, x, full, torch.tensor([[0.0, 0.0, 1.0]]).expand(2, 3)) == r2
    for mask in (torch.ones(7, dtype=torch.bool), torch.arange(7) < 4):
        fixed = _FixedEstimate(up, margin)
        up_report(fixed, torch.zeros(5, 7, 3), mask, z.expand(5, 3))
        assert all(m is (None if mask.all() else mask) for m in fixed.masks)
    assert format_up_report(r).startswith("up estimate: median error 45.0 deg, 2 of 5 views")


class _Head:
    candidates = icosahedral(3).pos.double()


class _LinesEstimate(nn.Module):
    """An up estimate whose answer is ``up`` and whose head scores directions by their
    cosine with ``favour`` (one per view)."""

    def __init__(self, up, favour):
        super().__init__()
        self.up, self.favour, self.seen, self.head = up, favour, 0, _Head()

    def forward(self, x, mask=None):
        s, self.seen = self.seen, self.seen + len(x)
        f = self.favour[s:self.seen]
        return {"up": self.up[s:self.seen], "margin": torch.ones(len(x)),
                "logits": 10 * f @ self.head.candidates.T}


def test_estimate_up_picks_among_line_axes_where_a_view_has_them():
    from usf_graph.train.gravity import estimate_up, up_report

    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    tilted = torch.nn.functional.normalize(torch.tensor([0.3, 0.0, 1.0], dtype=torch.float64), dim=0)
    frame = torch.stack([torch.tensor([0.0, 1.0, 0.0]), torch.tensor([1.0, 0.0, 0.0]), z]).double()
    axes = torch.stack([frame, torch.full((3, 3), float("nan"), dtype=torch.float64), frame])
    favour = torch.stack([-z, z, z])  # view 0's head prefers down, a sign the lines cannot give
    est = _LinesEstimate(tilted.expand(3, 3), favour)
    up, _ = estimate_up(est, torch.zeros(3, 5, 3), None, batch_size=2, axes=axes)
    # views 0 and 2 take the axis their head favours; view 1 has no axes and keeps its estimate
    assert torch.equal(up, torch.stack([-z, tilted, z]))
    r = up_report(_LinesEstimate(tilted.expand(3, 3), favour), torch.zeros(3, 5, 3), None,
                  z.expand(3, 3), axes=axes)
    assert r["lines"] == 2 and r["gross"] == 1 and r["median_err_deg"] == pytest.approx(
        np.degrees(np.arctan(0.3)), abs=0.01)
    with pytest.raises(ValueError, match=r"axes must be \[3, 3, 3\]"):
        estimate_up(est, torch.zeros(3, 5, 3), None, axes=axes[:2])


def test_lines_up_reads_a_pinholes_rendered_rooms_and_split_up_says_what_it_reads():
    """End to end: a room through a level and a tilted pinhole, each image's line axes, and
    a head that favours the true up picks an axis within 2.5 degrees of it. (Through other
    lenses: tests/frontend/test_lines.py.)"""
    from usf_graph.cameras import Equirectangular, Pinhole
    from usf_graph.geometry import rotation_from_axis_angle
    from usf_graph.scenes import make_room, render
    from usf_graph.train.gravity import lines_axes, lines_up, split_up

    cam = Pinhole(64.0, 64.0, 63.5, 63.5, 128, 128)
    images, ups = [], []
    scene = make_room(seed=3, index=3, materials="by_kind")
    for pitch, roll in ((0.0, 0.0), (25.0, 10.0)):
        pos, R = scene.viewpoint(0)
        R = R @ rotation_from_axis_angle(np.array([0.0, 1.0, 0.0]), np.radians(pitch)) \
            @ rotation_from_axis_angle(np.array([1.0, 0.0, 0.0]), np.radians(roll))
        images.append(render(scene, cam, pos, R, boxes=False).rgb)
        ups.append(R.T @ np.array([0.0, 0.0, 1.0]))
    g = torch.as_tensor(np.stack(ups))
    ds = SimpleNamespace(camera=cam, image=torch.as_tensor(np.stack(images)), x=torch.zeros(2, 5, 3),
                         mask=torch.ones(2, 5, dtype=torch.bool), gravity=g.float())
    est = _LinesEstimate(torch.zeros(2, 3, dtype=torch.float64), g)
    up, axes = lines_up(est, ds)
    err = np.degrees(np.arccos(np.clip((up * g).sum(-1).numpy(), -1, 1)))
    assert axes.shape == (2, 3, 3) and (err < 2.5).all()

    def model():
        return SimpleNamespace(gravity=_LinesEstimate(torch.nn.functional.normalize(g + 0.2, dim=-1), g))

    # an image without lines has NaN axes, and an empty split none
    blank = SimpleNamespace(camera=cam, image=torch.full((1, 128, 128, 3), 128, dtype=torch.uint8))
    assert lines_axes(blank).shape == (1, 3, 3) and lines_axes(blank).isnan().all()
    assert lines_axes(SimpleNamespace(camera=cam, image=blank.image[:0])).shape == (0, 3, 3)

    u = split_up(model(), ds, up_lines=True)
    assert torch.equal(u.up, up) and torch.equal(u.estimate, up) and torch.equal(u.axes, axes)
    assert u.report(g)["lines"] == 2 and u.report(g)["median_err_deg"] < 2.5
    # the true up is read, and the report is still the estimate's (the plain one here)
    known, own = split_up(model(), ds, known_up=True), split_up(model(), ds)
    assert known.up is ds.gravity and known.axes is None and torch.equal(known.estimate, own.up)
    assert torch.equal(own.up, own.estimate) and own.axes is None and known.report(g) == own.report(g)
    assert own.report(g)["median_err_deg"] > 5 and "lines" not in own.report(g)
    # a split without one camera (a rig's) has no lines to read: the estimate as it is; a
    # panorama's lines are read too (through pinholes), so its images must be its size
    rig = split_up(model(), SimpleNamespace(**{k: v for k, v in vars(ds).items() if k != "camera"}),
                   up_lines=True)
    assert torch.equal(rig.up, own.up) and rig.axes is None
    with pytest.raises(ValueError, match="the camera's"):
        split_up(model(), SimpleNamespace(**{**vars(ds), "camera": Equirectangular(8, 4)}), up_lines=True)
    # a planar model reads no up
    assert split_up(SimpleNamespace(input_dims=4), ds, up_lines=True) == (None,) * 4
    assert split_up(SimpleNamespace(gravity=None), ds).report(g) is None
    with pytest.raises(ValueError, match="exclude each other"):
        split_up(model(), ds, known_up=True, up_lines=True)
    with pytest.raises(ValueError, match="has none"):
        split_up(SimpleNamespace(gravity=None), ds, up_lines=True)


def test_an_up_batch_of_several_fields_of_view_is_refused():
    """The up step reads one field of view per batch: views of two cameras in one batch
    stop with the fix, rather than all being read through the first one's."""
    from torch_geometric.data import Batch

    from usf_graph.train.gravity import up_step

    g = icosahedral(2)
    net = UpNet(3, 2, channels=(4, 4))
    a, b = (g.pos[:, 0] > -0.2), (g.pos[:, 0] < 0.2)  # two caps: a front and a back camera
    views = [Data(x=torch.rand(len(g.pos), 3) * m[:, None], pos=g.pos.float(), mask=m) for m in (a, b, a)]
    with pytest.raises(ValueError, match=r"different fields of view.*field_groups"):
        up_step(net, Batch.from_data_list(views[:2]))
    loss, _, n = up_step(net, Batch.from_data_list(views[::2]))  # one camera: trained
    assert n == 2 and torch.isfinite(loss)


def test_known_up_is_the_batchs_gravity_or_plus_z_jittered_by_up_jitter():
    from usf_graph.train.gravity import UP_JITTER, known_up

    torch.manual_seed(0)
    x = torch.zeros(20000, 1, dtype=torch.float64)
    g, noisy = known_up(SimpleNamespace(), x)  # no up: gravity-aligned views
    assert g.dtype == torch.float64 and torch.equal(g, torch.tensor([0.0, 0.0, 1.0]).double().expand(20000, 3))
    d = noisy - g
    assert d.mean(0).abs().max() < 0.002 and ((d.std(0) / UP_JITTER - 1).abs() < 0.03).all()
    east = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    g2, _ = known_up(SimpleNamespace(up=east.reshape(-1)), x[:2])  # PyG concatenates [B * 3]
    assert torch.equal(g2, east.double())
    # a split's gravity from the first view on when no start is given
    assert torch.equal(given_up(torch.arange(12.0).view(4, 3), x[:2])["up"],
                       torch.arange(6.0).view(2, 3).double())


def test_split_mask_is_the_one_field_the_views_share():
    from usf_graph.train.gravity import split_mask

    part = torch.arange(6) < 4
    assert split_mask(SimpleNamespace()) is None and split_mask(SimpleNamespace(mask=None)) is None
    assert split_mask(SimpleNamespace(mask=part)) is part  # one [N] mask for the split
    assert torch.equal(split_mask(SimpleNamespace(mask=part.expand(3, 6))), part)
    with pytest.raises(ValueError, match="different fields of view.*evaluate_fields"):
        split_mask(SimpleNamespace(mask=torch.stack([part, ~part])))


def test_up_summary_rounds_the_median_to_hundredths_and_counts_line_views():
    from usf_graph.train.gravity import up_summary

    deg = torch.tensor([12.3456, 1.0, 30.0])
    up = torch.stack([torch.sin(torch.deg2rad(deg)), torch.zeros(3), torch.cos(torch.deg2rad(deg))], -1)
    axes = torch.stack([torch.eye(3), torch.full((3, 3), float("nan")), torch.eye(3)])
    r = up_summary(up, torch.full((3,), 9.0), torch.tensor([0.0, 0.0, 1.0]).expand(3, 3), axes)
    assert r == {"views": 3, "median_err_deg": 12.35, "gross": 0, "unsure": 0, "gross_unsure": 0,
                 "lines": 2}


class _RecordingUpNet(UpNet):
    """An :class:`UpNet` that records the masks it reads."""

    def forward(self, x, mask=None):
        self.masks = getattr(self, "masks", []) + [mask]
        return super().forward(x, mask)


def test_up_step_reads_the_batchs_field_of_view_or_a_random_cap_inside_it():
    from torch_geometric.data import Batch

    from usf_graph.train.gravity import UP_WEIGHT, up_step

    g = icosahedral(2)
    front = g.pos[:, 0] > -0.5
    views = [Data(x=torch.rand(len(g.pos), 3), pos=g.pos.float(), mask=front) for _ in range(2)]
    torch.manual_seed(0)
    net = _RecordingUpNet(3, 2, channels=(4, 4))
    up_step(net, Batch.from_data_list(views))
    assert torch.equal(net.masks[-1], front)  # the camera's field, not the whole sphere
    # the loss is UP_WEIGHT times the head's, and the stats its mean error in degrees
    out = net.eval()(torch.stack([v.x for v in views]), front)
    z = torch.tensor([[0.0, 0.0, 1.0]]).expand(2, 3)
    loss_eval, stats_eval, _ = up_step(net, Batch.from_data_list(views))
    net.train()
    assert torch.allclose(loss_eval, UP_WEIGHT * net.head.loss(out, z), rtol=1e-5)
    want = torch.rad2deg(torch.arccos(out["up"][:, 2].clamp(-1, 1))).mean()
    assert stats_eval["up_err_deg"] == pytest.approx(float(want), rel=1e-4)
    # through caps: a cap of 40-100 degrees inside the field of view, different per batch
    caps = []
    for _ in range(4):
        up_step(net, Batch.from_data_list(views), caps=1.0)
        caps.append(net.masks[-1])
    for m in caps:
        assert m is not None and bool((m <= front).all()) and 0 < int(m.sum()) < int(front.sum())
    assert len({tuple(m.tolist()) for m in caps}) > 1
    # a cap that misses the field of view keeps the field
    spot = g.pos[:, 2] > 0.99
    assert spot.any()
    one = [Data(x=torch.rand(len(g.pos), 3), pos=g.pos.float(), mask=spot) for _ in range(2)]
    torch.manual_seed(1)
    up_step(net, Batch.from_data_list(one), caps=1.0, cap_degrees=(1.0, 1.0))
    assert torch.equal(net.masks[-1], spot)


def test_up_views_renders_the_extra_panoramas_or_none(tmp_path):
    from usf_graph.datasets import RoomsGravity
    from usf_graph.train.gravity import up_views

    assert up_views(tmp_path, 0) is None
    v = up_views(tmp_path, 2, grid="icosahedral:2", progress=False)
    assert isinstance(v, RoomsGravity) and len(v) == 2 and v.grid.spec == "icosahedral:2"
    assert torch.equal(v[1].up, torch.tensor([[0.0, 0.0, 1.0]]))
