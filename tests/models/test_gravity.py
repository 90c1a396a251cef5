"""The gravity head: its scores are a whole-sphere distance-kernel convolution that a
hand-set field turns into an exact up detector; its loss and its errors."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from usf_graph import grids
from usf_graph.models import GravityHead
from usf_graph.models.gravity import heights, rank2_gap, symmetric_eigh3


def _set_cosine_detector(head: GravityHead, gain: float):
    """Weights that make the score ``gain * sum_m w_m f_m K(theta_nm)`` with a kernel
    decreasing in theta (the bumps weighted by cos of their centres), for a 1-channel f."""
    K, H = head.num_basis, head.hidden
    centers = torch.linspace(0, math.pi, K, dtype=torch.float64)
    with torch.no_grad():
        head.field.weight.zero_()
        head.field.bias.zero_()
        head.field.weight.view(K, H, 1)[:, 0, 0] = torch.cos(centers)
        head.bias.fill_(10.0)  # keeps the ReLU linear
        head.score.weight.zero_()
        head.score.weight[0, 0] = gain
        head.score.bias.zero_()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_up_is_found_from_a_field_that_is_high_up_and_low_down(seed):
    """A field f = p . g (a "height" image) makes the hand-set head point at g: the scores
    peak at the candidate nearest g and the soft-argmax lands within a degree of it."""
    gen = torch.Generator().manual_seed(seed)
    coarse = grids.icosahedral(2)
    head = GravityHead(coarse, channels=1).double()
    _set_cosine_detector(head, gain=400.0)
    g = torch.nn.functional.normalize(torch.randn(3, 3, generator=gen, dtype=torch.float64), dim=-1)
    f = (g @ coarse.pos.double().T)[..., None]  # [B, M, 1]
    out = head(f)
    cand = head.candidates
    nearest = (g @ cand.T).argmax(-1)
    assert (out["logits"].argmax(-1) == nearest).all()
    err = torch.rad2deg(torch.arccos((out["up"] * g).sum(-1).clamp(-1, 1)))
    assert (err < 1.5).all(), err
    assert torch.allclose(out["up"].norm(dim=-1), torch.ones(3, dtype=torch.float64))
    # the same field upside down points the other way
    down = head(-f)["up"]
    assert ((down * g).sum(-1) < -0.99).all()
    # heights along the estimate are each point's elevation
    torch.testing.assert_close(heights(coarse.pos, out["up"])[..., 0], (out["up"] @ coarse.pos.double().T))


def test_hidden_points_do_not_vote():
    coarse = grids.icosahedral(2)
    head = GravityHead(coarse, channels=1).double()
    _set_cosine_detector(head, gain=400.0)
    g = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    mask = coarse.pos[:, 0] > -0.2
    f = (g @ coarse.pos.double().T)[..., None]
    junk = f.clone()
    junk[:, ~mask] = 100.0
    a, b = head(f, mask), head(junk, mask)
    torch.testing.assert_close(a["logits"], b["logits"])
    assert not torch.allclose(head(junk)["logits"], a["logits"])


def test_loss_prefers_scores_peaked_at_the_true_up():
    torch.manual_seed(0)  # a ReLU unit dead on every input gets no gradient: not by chance
    coarse = grids.icosahedral(1)
    head = GravityHead(coarse, channels=1).double()
    g = torch.nn.functional.normalize(torch.tensor([[0.3, -0.2, 1.0]], dtype=torch.float64), dim=-1)
    q = head.target(g)
    assert torch.allclose(q.sum(-1), torch.ones(1, dtype=torch.float64))
    assert q.argmax(-1) == (g @ head.candidates.T).argmax(-1)
    right = head.loss({"logits": torch.log(q)}, g)
    wrong = head.loss({"logits": torch.log(head.target(-g))}, g)
    flat = head.loss({"logits": torch.zeros_like(q)}, g)
    # cross-entropy: the entropy of the target at its minimum
    torch.testing.assert_close(right, -(q * q.log()).sum())
    assert right < flat < wrong
    # and it trains the head's parameters
    f = torch.randn(2, len(coarse), 1, dtype=torch.float64)
    head.loss(head(f), g.expand(2, 3)).backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in head.parameters())


def test_sign_weight_penalizes_scoring_down_above_up():
    coarse = grids.icosahedral(1)
    head = GravityHead(coarse, channels=1).double()
    g = torch.nn.functional.normalize(torch.tensor([[0.3, -0.2, 1.0]], dtype=torch.float64), dim=-1)
    up, down = head.target(g), head.target(-g)

    def extra(logits, w=0.5):
        return head.loss({"logits": logits}, g, sign_weight=w) - head.loss({"logits": logits}, g)

    # scores even under g -> -g: softplus(0) = log 2, whatever the scores' size
    even = 7.0 * (up + down)
    torch.testing.assert_close(extra(even), torch.tensor(0.5 * math.log(2), dtype=torch.float64))
    # a margin of m for up costs about w e^-m; for down, about w m
    m = 20.0
    torch.testing.assert_close(extra(m * up / (up * up).sum()), torch.tensor(0.0, dtype=torch.float64),
                               atol=1e-8, rtol=0)
    torch.testing.assert_close(extra(m * down / (down * down).sum()),
                               torch.tensor(0.5 * m, dtype=torch.float64), atol=1e-6, rtol=0)
    assert extra(torch.zeros_like(up), 0.0) == 0  # off by default


def test_upnet_errors_and_where_it_starts():
    from usf_graph.models import UpNet

    with pytest.raises(ValueError, match="coarsen"):
        UpNet(3, 3, channels=(4, 4, 4, 4))
    assert UpNet(3, 3, channels=(4, 4), coarsen=0).pre is None
    net = UpNet(3, 3, channels=(4, 4)).double()
    x = torch.randn(2, len(grids.icosahedral(3)), 3, dtype=torch.float64)
    assert net(x)["up"].shape == (2, 3) and net.head.pos.shape == (len(grids.icosahedral(1)), 3)
    # a diverged run's NaN weights say so, not a linear-algebra failure in the polish
    with torch.no_grad():
        net.head.score.weight.fill_(float("nan"))
    with pytest.raises(ValueError, match="scores are NaN or inf"):
        net.eval()(x)


def test_upnet_is_built_as_its_docstring_says():
    """Pooled ``coarsen`` levels down, the jet there reaching ``jet_spacings`` spacings, one
    stage per entry of ``channels`` on successively coarser levels with kernel radius
    ``radius_spacings`` spacings, blurs of half a coarse spacing between them."""
    from usf_graph.geometry import geodesic_distance
    from usf_graph.models import UpNet
    from usf_graph.models.stages import level_spacing as h

    net = UpNet(3, 4, channels=(4, 4, 4), radius_spacings=2.5, jet_spacings=3.0)
    assert [c.radius for st in net.stages for c in st.convs] == pytest.approx([2.5 * h(lv) for lv in (3, 2, 1)])
    assert net.pre.sigma == pytest.approx(0.5 * h(3))
    assert [p.sigma for p in net.pools] == pytest.approx([0.5 * h(2), 0.5 * h(1)])
    assert net.jet.spacing == pytest.approx(h(3))
    # the jet's fit reaches 3 spacings: a spike moves the derivatives of its points only
    pos = grids.icosahedral(3).pos
    spike = torch.zeros(1, len(pos), 1, dtype=torch.float64)
    spike[0, 7] = 1.0
    moved = net.jet.double()(spike)[0, :, 1:].abs().amax(-1) > 1e-4
    d = geodesic_distance(pos, pos[7:8].expand_as(pos))
    assert d[moved].max() <= 3.0 * h(3) and d[moved].max() > 2.0 * h(3)
    assert net.head.pos.shape == (len(grids.icosahedral(1)), 3)


def test_the_up_estimate_runs_only_where_it_is_read():
    """Given an up, a model skips its estimate in evaluation unless asked for it; in
    training a trainable one runs (its loss reads it), a frozen one does not."""
    from usf_graph.models import SphericalDetector, SphericalUNet

    seg = SphericalUNet(num_classes=3, level=3, min_level=2, channels=(4, 4), gravity=True)
    det = SphericalDetector(num_classes=3, input_level=3, head_level=2, min_level=1,
                            channels=(4, 4, 4), pairs=2, gradient_fields=2, gravity=True)
    x = torch.rand(2, len(grids.icosahedral(3)), 3)
    up = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    runs = []
    for model in (seg, det):
        model.gravity.register_forward_hook(lambda *_: runs.append(1))

    def ran(model, **kw):
        runs.clear()
        with torch.no_grad():
            model(x, **kw)
        return len(runs)

    for model in (seg, det):
        model.eval()
        assert ran(model, up=up) == 0 and ran(model) == 1
        model.train()
        assert ran(model, up=up) == 1
        model.gravity.requires_grad_(False)
        assert ran(model, up=up) == 0
        model.gravity.requires_grad_(True)
    seg.eval()
    with torch.no_grad():
        _, grav = seg(x, up=up, return_gravity=True)  # asked for: it runs
    assert grav is not None and grav["up"].shape == (2, 3)
    det.eval()
    with torch.no_grad():
        assert "gravity" not in det(x, up=up) and "gravity" in det(x)


def test_upnet_polishes_its_estimate_in_evaluation_only():
    from usf_graph.models import UpNet

    torch.manual_seed(0)
    net = UpNet(3, 3, channels=(4, 4)).double()
    x = torch.rand(2, len(grids.icosahedral(3)), 3, dtype=torch.float64)
    mask = grids.icosahedral(3).pos[:, 2] > -0.5
    assert "up_head" not in net(x, mask)  # training: the head's estimate, which the loss trains
    ev = net.eval()(x, mask)
    torch.testing.assert_close(ev["up"], net.polish(x, mask, ev["up_head"]))
    assert not torch.allclose(ev["up"], ev["up_head"])  # it did polish
    assert UpNet(3, 3, channels=(4, 4), polish=False).polish is None


def test_loss_adds_the_area_weighted_height_error_of_the_visible_points():
    coarse = grids.icosahedral(1)
    head = GravityHead(coarse, channels=2).double()
    g = torch.tensor([[0.0, 0.6, 0.8]], dtype=torch.float64)
    mask = coarse.pos[:, 0] > -0.3
    out = head(torch.randn(1, len(coarse), 2, dtype=torch.float64), mask)
    ce = head.loss({"logits": out["logits"]}, g)
    w = coarse.area.double() * mask
    mse = ((out["height"] - g @ coarse.pos.double().T) ** 2 * w).sum() / w.sum()
    torch.testing.assert_close(head.loss(out, g), ce + mse)
    exact = {**out, "height": g @ coarse.pos.double().T}
    torch.testing.assert_close(head.loss(exact, g), ce)


def _edge_votes(level=4):
    from usf_graph.models.gravity import EdgeVotes
    from usf_graph.models.stages import level_spacing

    g = grids.icosahedral(level)
    ev = EdgeVotes(g, grids.icosahedral(3).pos, features=1, spacing=level_spacing(level)).double()
    with torch.no_grad():  # the same weight for every edge
        ev.weight.weight.zero_()
        ev.weight.bias.fill_(1.0)
    return g, ev


@pytest.mark.parametrize("seed", [0, 1])
def test_edge_votes_point_at_the_axis_all_edges_run_through(seed):
    """Stripes along the meridians of an axis a (a function of the longitude about a only)
    have every edge on a great circle through +-a: the votes peak at +-a, and nowhere near
    the directions the edges run across."""
    gen = torch.Generator().manual_seed(seed)
    g, ev = _edge_votes()
    a = torch.nn.functional.normalize(torch.randn(3, generator=gen, dtype=torch.float64), dim=0)
    e1 = torch.nn.functional.normalize(torch.linalg.cross(a, torch.randn(3, generator=gen, dtype=torch.float64)), dim=0)
    e2 = torch.linalg.cross(a, e1)
    p = g.pos.double()
    lon = torch.atan2(p @ e2, p @ e1)
    x = torch.stack([torch.sin(5 * lon), torch.cos(3 * lon)], -1)[None]  # [1, N, 2]
    v = ev(x, torch.zeros(1, len(p), 1, dtype=torch.float64))[0]
    best = ev.candidates[v.argmax()]
    assert math.degrees(math.acos(min(1.0, abs(float(best @ a))))) < 8
    # candidates at 90 degrees from a get the votes of one meridian at most, not of all
    side = (ev.candidates @ a).abs() < 0.2
    assert v[side].max() < 0.65 * v.max()


@pytest.mark.parametrize("level", [4, 5])
def test_edge_votes_stay_finite_and_bounded_in_float32(level):
    """Each edge's vote is its weight times s2 exp(-kappa e), s2 and e squared sines, so the
    votes over the weights' sum lie in [0, 1]. In float32 a candidate that is itself an edge
    point (the grids are nested) had a^T T a rounded below 0, and exp(-kappa e) blew it up:
    NaN votes on these ramps from a gradient of 10 per radian, on level 4 too (session 36;
    on the detection protocol's views, e reached -0.66)."""
    g, ev = _edge_votes(level)
    ev, p = ev.float(), g.pos.float()
    gen = torch.Generator().manual_seed(level)
    for scale in (1.0, 10.0, 50.0):  # colour ramps: strong edges everywhere, candidates too
        d = torch.nn.functional.normalize(torch.randn(3, 3, generator=gen), dim=0)
        x = (scale * p @ d)[None] + 0.01 * torch.rand(1, len(p), 3, generator=gen)
        with torch.no_grad():
            v = ev(x, torch.zeros(1, len(p), 1)) / ev.scale
        assert torch.isfinite(v).all() and v.min() >= 0 and v.max() <= 1 + 1e-6, scale


def test_edge_votes_ignore_hidden_points():
    """Edges outside the field of view do not vote: changing the image far inside the
    hidden part changes nothing."""
    g, ev = _edge_votes()
    p = g.pos.double()
    mask = p[:, 0] > 0.3  # a cap
    x = torch.randn(1, len(p), 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    f = torch.randn(1, len(p), 1, dtype=torch.float64)
    x2 = x.clone()
    far = p[:, 0] < -0.2  # beyond the jet's reach from every visible point
    x2[:, far] = 10 * torch.randn(1, int(far.sum()), 3, dtype=torch.float64)
    assert torch.allclose(ev(x, f, mask), ev(x2, f, mask), rtol=0, atol=1e-12)
    assert not torch.allclose(ev(x, f), ev(x2, f))  # without the mask they do vote


def _structure(jet, x):
    """Colour structure tensors of ``x [1, N, C]``, rebuilt from the jet's gradients, and
    their traces, for the formula tests' references."""
    from usf_graph.models.gravity import structure_tensors

    T, tr = structure_tensors(jet, x)
    return T[0], tr[0]


def test_edge_votes_are_the_documented_sum():
    """V_n = scale * sum_m w_m s_nm^2 exp(-kappa e_nm) / sum_m w_m over the topk strongest
    visible edges, with s^2 = 1 - (a_n . p_m)^2, e = a_n^T T_m a_n / (tr T_m s^2) clamped
    at 0 and w_m = softplus of the features' linear map, written out per candidate."""
    gen = torch.Generator().manual_seed(7)
    g, ev = _edge_votes(level=3)
    ev.topk = 50
    p = g.pos.double()
    x = torch.sin(p @ (3 * torch.randn(3, 2, generator=gen, dtype=torch.float64)) + 1)[None]
    f = torch.randn(1, len(p), 2, generator=gen, dtype=torch.float64)
    ev.weight = torch.nn.Linear(2, 1).double()
    mask = p[:, 2] > -0.3
    v = ev(x, f, mask)[0]
    T, tr = _structure(ev.jet, x)
    order = torch.argsort(torch.where(mask, tr, -1.0), descending=True)
    top = order[:50]
    assert tr[order[49]] > tr[order[50]]  # no tie decides which edges vote
    w = torch.nn.functional.softplus(ev.weight(f[0, top]))[:, 0]
    want = torch.zeros(len(ev.candidates), dtype=torch.float64)
    for n, a in enumerate(ev.candidates):
        for wm, m in zip(w, top):
            s2 = 1 - float(a @ p[m]) ** 2
            if s2 > 1e-12:  # a candidate on the edge point votes 0 (s^2 = 0)
                e = max(float(a @ T[m] @ a) / (float(tr[m]) * s2), 0.0)
                want[n] += wm * s2 * math.exp(-ev.kappa * e)
    want = ev.scale.detach() * want / w.sum()
    assert want.max() > 3 * want.min()  # the votes differ between candidates
    torch.testing.assert_close(v.detach(), want, rtol=1e-4, atol=1e-6)


def test_one_polish_step_is_the_documented_reweighted_fit():
    """One step from u0: u = the eigenvector of the smallest eigenvalue of
    sum_m c_m^2 exp(-kappa e_m(u0)) T_m / tr T_m over the topk strongest edges, with c_m the
    gap of the two nonzero eigenvalues of T_m / tr T_m and e_m(u0) = u0^T T_m u0 / (tr T_m (1 -
    (u0 . p_m)^2)), signed like u0; written out with LAPACK's eigendecompositions."""
    gen = torch.Generator().manual_seed(8)
    g, polish = _polish(level=3, topk=200, kappas=(20.0,), max_step=math.pi)
    p = g.pos.double()
    x = _meridian_stripes(p, torch.tensor([0.0, 0.6, 0.8], dtype=torch.float64), gen)
    x = x + 0.2 * torch.randn(x.shape, generator=gen, dtype=torch.float64)
    u0 = torch.nn.functional.normalize(torch.tensor([0.3, 0.5, 0.7], dtype=torch.float64), dim=0)
    T, tr = _structure(polish.jet, x)
    top = torch.argsort(tr, descending=True)[:200]
    M = torch.zeros(3, 3, dtype=torch.float64)
    for m in top:
        Tn = T[m] / tr[m]
        lam = torch.linalg.eigvalsh(Tn)
        e = float(u0 @ Tn @ u0) / (1 - float(u0 @ p[m]) ** 2)
        M += float(lam[2] - lam[1]) ** 2 * math.exp(-20.0 * max(e, 0.0)) * Tn
    want = torch.linalg.eigh(M)[1][:, 0]
    want = want if float(want @ u0) > 0 else -want
    u = polish(x, None, u0[None])[0]
    assert _deg(u, u0) > 1  # the step moves it
    torch.testing.assert_close(u, want, rtol=0, atol=1e-9)


def _polish(level=4, **kw):
    from usf_graph.models.gravity import UpPolish
    from usf_graph.models.stages import level_spacing

    g = grids.icosahedral(level)
    return g, UpPolish(g, level_spacing(level), **kw)


def _meridian_stripes(p: torch.Tensor, a: torch.Tensor, gen) -> torch.Tensor:
    """A colour image that depends on the longitude about ``a`` only: every edge lies on
    a great circle through +-a (as vertical lines do through up)."""
    e1 = torch.nn.functional.normalize(torch.linalg.cross(a, torch.randn(3, generator=gen, dtype=torch.float64)), dim=0)
    lon = torch.atan2(p @ torch.linalg.cross(a, e1), p @ e1)
    return torch.stack([torch.sin(5 * lon), torch.cos(3 * lon), torch.sin(7 * lon + 1)], -1)[None]


def _tilt(a: torch.Tensor, deg: float, gen) -> torch.Tensor:
    v = torch.nn.functional.normalize(torch.linalg.cross(a, torch.randn(3, generator=gen, dtype=torch.float64)), dim=0)
    return math.cos(math.radians(deg)) * a + math.sin(math.radians(deg)) * v


def _deg(u: torch.Tensor, v: torch.Tensor) -> float:
    return math.degrees(math.acos(min(1.0, float(u @ v))))


@pytest.mark.parametrize("seed", range(3))
def test_rank2_gap_is_the_squared_gap_of_the_two_nonzero_eigenvalues(seed):
    """Against LAPACK's eigenvalues, on sums of outer products of tangent vectors (the
    structure tensors' kind), near-isotropic ones and single edges included."""
    g = torch.Generator().manual_seed(seed)
    p = torch.nn.functional.normalize(torch.randn(200, 3, generator=g, dtype=torch.float64), dim=-1)
    v = torch.randn(200, 5, 3, generator=g, dtype=torch.float64)
    v = v - (v * p[:, None]).sum(-1, keepdim=True) * p[:, None]  # tangent at p
    v[:50, 1:] = 0  # one edge: the gap is the whole trace
    T = torch.einsum("bki,bkj->bij", v, v)
    ev = torch.linalg.eigvalsh(T)
    assert ev[:, 0].abs().max() < 1e-12 * ev[:, 2].max()
    np.testing.assert_allclose(rank2_gap(T), (ev[:, 2] - ev[:, 1]) ** 2, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(rank2_gap(T[:50]), ev[:50, 2] ** 2, rtol=1e-9)
    assert (rank2_gap(torch.eye(3, dtype=torch.float64).expand(4, 3, 3).clone() -
                      torch.diag(torch.tensor([0.0, 0, 1], dtype=torch.float64))) == 0).all()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_polish_pulls_an_estimate_onto_the_axis_the_edges_run_through(seed):
    gen = torch.Generator().manual_seed(seed)
    g, polish = _polish()
    p = g.pos.double()
    a = torch.nn.functional.normalize(torch.randn(3, generator=gen, dtype=torch.float64), dim=0)
    x = _meridian_stripes(p, a, gen)
    for sign in (1, -1):  # up or down: the fit keeps the estimate's hemisphere
        u0 = _tilt(sign * a, 15.0, gen)
        u = polish(x, None, u0[None])[0]
        assert _deg(u, sign * a) < 0.5 < 14 < _deg(u0, sign * a)
        assert abs(float(u.norm()) - 1) < 1e-12


def test_polish_never_moves_far_and_keeps_the_estimate_without_edges():
    gen = torch.Generator().manual_seed(3)
    g, polish = _polish()
    p = g.pos.double()
    a = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    x = _meridian_stripes(p, a, gen)
    u0 = _tilt(a, 50.0, gen)[None]  # beyond max_step (30 degrees) of the axis
    assert _deg(polish(x, None, u0)[0], u0[0]) <= 30 + 1e-9
    flat = torch.ones(1, len(p), 3, dtype=torch.float64)  # no edges: nothing to fit
    assert torch.equal(polish(flat, None, u0), u0)
    # a field of view that misses every edge: the same
    mask = p[:, 0] > 0.5
    x2 = x.clone()
    x2[:, mask] = 0.5
    assert torch.equal(polish(x2, mask, u0), u0)


def test_polish_rotates_with_the_input_and_ignores_hidden_points():
    from usf_graph.testing import symmetry_permutation

    gen = torch.Generator().manual_seed(4)
    g, polish = _polish(level=3, topk=256)
    p = g.pos.double()
    a = torch.nn.functional.normalize(torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64), dim=0)
    x = _meridian_stripes(p, a, gen) + 0.05 * torch.randn(1, len(p), 3, generator=gen, dtype=torch.float64)
    u0 = _tilt(a, 10.0, gen)[None]
    R = _vertex_rotation(p[0])  # maps the grid onto itself
    mask = p @ p[0] > -0.4  # symmetric about the rotation axis
    xr = torch.empty_like(x)
    xr[:, symmetry_permutation(p, R)] = x
    u, ur = polish(x, mask, u0), polish(xr, mask, u0 @ R.T)
    assert _deg(u[0], u0[0]) > 2  # it did move
    assert torch.allclose(ur, u @ R.T, atol=1e-9)
    y = x.clone()
    y[:, ~mask] = torch.randn(1, int((~mask).sum()), 3, generator=gen, dtype=torch.float64)
    assert torch.equal(polish(y, mask, u0), u)


def test_polish_survives_an_edge_right_at_the_estimate_in_float32():
    """At an edge point p = u the squared sine e = u^T T u / (1 - (u.p)^2) is 0 / 0, and
    float32 rounding makes the numerator slightly negative: that must not blow up."""
    gen = torch.Generator().manual_seed(5)
    g, polish = _polish()
    p = g.pos.double()
    x = _meridian_stripes(p, torch.tensor([0.0, 0.6, 0.8], dtype=torch.float64), gen).float()
    x = x + 0.3 * torch.randn(x.shape, generator=gen)
    u0 = g.pos[torch.randperm(len(p), generator=gen)[:64]].float()  # estimates on edge points
    u = polish(x.expand(64, -1, -1), None, u0)
    assert u.dtype == torch.float32 and torch.isfinite(u).all()
    assert torch.allclose(u.norm(dim=-1), torch.ones(64), atol=1e-6)


def _vertex_rotation(axis: torch.Tensor, turns: int = 1) -> torch.Tensor:
    """A rotation by ``turns`` fifths of a turn about ``axis``: a symmetry of the
    icosahedral grids when ``axis`` is one of their vertices."""
    K = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    t = 2 * math.pi * turns / 5
    return torch.eye(3, dtype=torch.float64) + math.sin(t) * K + (1 - math.cos(t)) * K @ K


@pytest.mark.parametrize("seed", [0, 1])
def test_margin_is_the_lead_of_the_best_score_over_directions_45_degrees_away(seed):
    """Checked against the definition, written with angles in degrees: the best score minus
    the best among candidates more than 45 degrees from the best candidate."""
    gen = torch.Generator().manual_seed(seed)
    coarse = grids.icosahedral(2)
    torch.manual_seed(seed)
    head = GravityHead(coarse, channels=3).double()
    out = head(torch.randn(4, len(coarse), 3, generator=gen, dtype=torch.float64))
    cand = head.candidates.numpy()
    for logits, margin in zip(out["logits"].detach().numpy(), out["margin"].detach().numpy()):
        best = cand[logits.argmax()]
        deg = np.degrees(np.arccos(np.clip(cand @ best, -1, 1)))
        assert margin == pytest.approx(logits.max() - logits[deg > 45].max(), abs=1e-12)
        assert margin >= 0


def test_margin_is_zero_on_a_blank_image_and_grows_with_the_evidence():
    """No content, no preferred direction: every candidate ties, margin 0 (below
    UNSURE_MARGIN). A "height" field makes one direction win, by more the stronger it is."""
    from usf_graph.models.gravity import UNSURE_MARGIN

    coarse = grids.icosahedral(2)
    head = GravityHead(coarse, channels=1).double()
    _set_cosine_detector(head, gain=400.0)
    g = torch.nn.functional.normalize(torch.tensor([[0.2, -0.4, 0.9]], dtype=torch.float64), dim=-1)
    f = (g @ coarse.pos.double().T)[..., None]
    with torch.no_grad():
        assert float(head(torch.zeros_like(f))["margin"]) == 0.0
        weak, strong = head(0.01 * f)["margin"], head(f)["margin"]
    assert float(weak) < UNSURE_MARGIN < float(strong)
    torch.testing.assert_close(strong, 100 * weak)  # linear in the evidence here


def test_margin_does_not_change_when_the_image_rotates():
    from usf_graph.testing import symmetry_permutation

    gen = torch.Generator().manual_seed(3)
    coarse = grids.icosahedral(2)
    torch.manual_seed(3)
    head = GravityHead(coarse, channels=2).double()
    p = coarse.pos.double()
    R = _vertex_rotation(p[5], turns=2)
    f = torch.randn(2, len(p), 2, generator=gen, dtype=torch.float64)
    fr = torch.empty_like(f)
    fr[:, symmetry_permutation(p, R)] = f
    a, b = head(f), head(fr)
    torch.testing.assert_close(b["margin"], a["margin"], rtol=0, atol=1e-10)
    torch.testing.assert_close(b["up"], a["up"] @ R.T, rtol=0, atol=1e-10)


def _cap(pos: torch.Tensor, axis, degrees: float) -> torch.Tensor:
    axis = torch.nn.functional.normalize(torch.as_tensor(axis, dtype=torch.float64), dim=0)
    return pos.double() @ axis > math.cos(math.radians(degrees))


def test_level_scores_are_minus_beta_times_the_squared_projection_on_the_mean_view():
    """Against the formula with m computed here in numpy, the visible points' area-weighted
    mean; and its size for the protocols' lenses."""
    from usf_graph.models.gravity import level_scores

    grid, cand = grids.icosahedral(4), grids.icosahedral(2).pos.double()
    pos, area = grid.pos.double(), grid.area.double()
    mask = _cap(pos, [1.0, 0.3, -0.2], 50)
    got = level_scores(cand, pos, area, mask, 7.0).numpy()
    w = area.numpy() * mask.numpy()
    m = (w[:, None] * pos.numpy()).sum(0) / w.sum()
    np.testing.assert_allclose(got, -7.0 * (cand.numpy() @ m) ** 2 / np.linalg.norm(m), rtol=0, atol=1e-12)
    # |m| = (1 + cos r) / 2 for a cap of radius r: 0.82 here, 0.46 for a 190-degree fisheye
    assert np.linalg.norm(m) == pytest.approx((1 + math.cos(math.radians(50))) / 2, abs=0.01)
    fisheye = level_scores(cand, pos, area, _cap(pos, [0, 1.0, 0], 95), 1.0)
    assert float(-fisheye.min()) == pytest.approx((1 + math.cos(math.radians(95))) / 2, abs=0.01)
    # the whole sphere has no mean direction: nothing
    everything = torch.ones(len(pos), dtype=torch.bool)
    assert level_scores(cand, pos, area, everything, 7.0).abs().max() < 1e-9
    with pytest.raises(ValueError, match="sees no point"):
        level_scores(cand, pos, area, torch.zeros_like(everything), 7.0)


def _level_net():
    from usf_graph.models import UpNet

    torch.manual_seed(0)
    return UpNet(3, 3, channels=(4, 4)).double().eval()


def test_level_prior_turns_an_up_along_the_optical_axis_across_it():
    """An UpNet whose own scores say "up is the optical axis" (a huge bias towards the
    candidate there, through the head's ``extra`` scores): without the prior it agrees;
    with a strong one it picks a direction across the axis, as a level camera's up is,
    and the margin (read from the same scores) follows."""
    net = _level_net()
    net.polish = None
    pos = net.view_pos
    axis = torch.nn.functional.normalize(torch.tensor([1.0, 0.2, 0.1], dtype=torch.float64), dim=0)
    mask = _cap(pos, axis, 45)
    x = torch.randn(2, len(pos), 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    head_forward = net.head.forward
    towards_axis = 30.0 * (net.head.candidates @ axis)
    net.head.forward = lambda f, m=None, extra=None: head_forward(
        f, m, towards_axis if extra is None else extra + towards_axis)
    with torch.no_grad():
        free = net(x, mask)["up"]
        net.level_prior = 1000.0
        level = net(x, mask)["up"]
        whole = net(x)["up"]  # no field of view: no prior
        net.level_prior = 0.0
        torch.testing.assert_close(net(x)["up"], whole, rtol=0, atol=0)
    assert (free @ axis > 0.95).all()
    assert ((level @ axis).abs() < math.sin(math.radians(10))).all()  # the candidates' spacing


def test_level_prior_adds_its_scores_to_the_edge_votes():
    from usf_graph.models.gravity import level_scores

    net = _level_net()
    assert net.votes is not None
    pos = net.view_pos
    mask = _cap(pos, [1.0, 0.2, 0.1], 60)
    x = torch.randn(2, len(pos), 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        off = net(x, mask)["logits"]
        net.level_prior = 3.0
        on = net(x, mask)["logits"]
    want = level_scores(net.head.candidates, pos, net.view_area, mask, 3.0)
    torch.testing.assert_close(on - off, want.expand_as(on), rtol=0, atol=1e-9)


def test_level_prior_keeps_the_estimate_equivariant():
    from usf_graph.testing import symmetry_permutation

    net = _level_net()
    net.level_prior = 5.0
    p = net.view_pos
    R = _vertex_rotation(p[7], turns=2)
    perm = symmetry_permutation(p, R)
    x = torch.randn(2, len(p), 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    mask = _cap(p, [0.3, -1.0, 0.4], 70)
    xr, mr = torch.empty_like(x), torch.empty_like(mask)
    xr[:, perm], mr[perm] = x, mask
    with torch.no_grad():
        a, b = net(x, mask), net(xr, mr)
        net.level_prior = 0.0
        off = net(x, mask)
    torch.testing.assert_close(b["up"], a["up"] @ R.T, rtol=0, atol=1e-9)
    torch.testing.assert_close(b["margin"], a["margin"], rtol=0, atol=1e-9)
    assert (off["logits"] - a["logits"]).abs().max() > 1  # it did act


def test_set_level_prior_reaches_every_up_estimate_and_checks_its_value():
    from usf_graph.models import SphericalUNet, set_level_prior

    net = _level_net()
    assert net.level_prior == 0.0
    assert set_level_prior(net, 10) == 1 and net.level_prior == 10.0
    assert set_level_prior(torch.nn.Linear(2, 2), 10) == 0
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="level_prior must be a finite number >= 0"):
            set_level_prior(net, bad)
    assert net.level_prior == 10.0  # a bad value changes nothing
    seg = SphericalUNet(num_classes=3, level=3, channels=(4, 4), gravity=True)
    assert set_level_prior(seg, 2.5) == 1 and seg.gravity.level_prior == 2.5
    assert seg.refined(1).gravity.level_prior == 2.5  # the finer grid's copy keeps it


def test_pick_axis_takes_the_signed_axis_the_head_scores_highest():
    from usf_graph.geometry import random_rotation
    from usf_graph.models.gravity import pick_axis

    cand = grids.icosahedral(3).pos.double()
    axes = torch.stack([random_rotation(generator=torch.Generator().manual_seed(s)).double().T
                        for s in (1, 2)])  # rows: each view's frame
    want = torch.stack([-axes[0, 1], axes[1, 2]])
    logits = 10 * want @ cand.T  # highest at the candidates nearest the wanted directions
    up = pick_axis(logits, cand, axes)
    # the axis itself, not the candidate near it: the lines place up, the head picks
    assert torch.equal(up, want)
    with pytest.raises(ValueError, match=r"axes must be \[B, 3, 3\]"):
        pick_axis(logits, cand, axes[:1])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU (CI has none)")
def test_on_a_gpu_the_polish_of_a_protocol_batch_follows_the_cpu_in_little_memory():
    """Session 40's crash, rerun: 16 views of the protocol's level-5 grid, its 2,048
    strongest edges each. CUDA's batched ``eigvalsh`` once asked 16.57 GiB for their gaps;
    the closed form (``rank2_gap``) needs a few MiB, and the polished ups match the CPU's."""
    gen = torch.Generator().manual_seed(0)
    g, polish = _polish(level=5)
    p = g.pos.double()
    axes = torch.nn.functional.normalize(torch.randn(16, 3, generator=gen, dtype=torch.float64), dim=-1)
    x = torch.cat([_meridian_stripes(p, a, gen) for a in axes]).float()
    u0 = torch.stack([_tilt(a, 15.0, gen) for a in axes]).float()
    mask = p[:, 0] > -0.5
    cpu = polish(x, mask, u0)
    torch.cuda.reset_peak_memory_stats()
    gpu = polish.cuda()(x.cuda(), mask.cuda(), u0.cuda()).cpu()
    assert torch.cuda.max_memory_allocated() < 2**30
    assert max(_deg(a.double(), b.double()) for a, b in zip(cpu, gpu)) < 0.05
    assert max(_deg(u.double(), a) for u, a in zip(gpu, axes)) < 1.0


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10_000), repeated=st.sampled_from([None, (0, 1), (1, 2), (0, 1, 2)]),
       scale=st.floats(1e-6, 1e6))
def test_jacobi_eigh3_is_torchs_eigendecomposition(seed, repeated, scale):
    """The polish's plain form: ascending eigenvalues to float64's precision, orthonormal
    eigenvectors with A v = lambda v, on random symmetric matrices, repeated eigenvalues
    and diagonal ones included."""
    gen = torch.Generator().manual_seed(seed)
    lam = torch.randn(4, 3, generator=gen, dtype=torch.float64) * scale
    if repeated is not None:
        lam[:, list(repeated)] = lam[:, repeated[0]:repeated[0] + 1]
    Q = torch.linalg.qr(torch.randn(4, 3, 3, generator=gen, dtype=torch.float64))[0]
    A = Q @ torch.diag_embed(lam) @ Q.transpose(1, 2)
    A = torch.cat([A, torch.diag_embed(lam[:1])])  # already diagonal: no rotation at all
    A = (A + A.transpose(1, 2)) / 2
    val, vec = symmetric_eigh3(A)
    ref = torch.linalg.eigvalsh(A)
    big = A.abs().amax((1, 2), keepdim=True).clamp_min(1e-300)
    assert ((val - ref).abs() / big[..., 0]).max() < 1e-13
    assert ((A @ vec - vec * val[:, None, :]).abs() / big).max() < 1e-13
    assert (vec.transpose(1, 2) @ vec - torch.eye(3, dtype=torch.float64)).abs().max() < 1e-13


def test_head_scores_are_the_documented_convolution_at_the_candidates():
    """s_n = v^T ReLU(U_n + b), U_n the area-weighted mean over the visible points of
    sum_k phi_k(theta_nm) W_k f_m, phi_k Gaussian bumps centred at k pi / (K - 1) with
    that spacing as their width; written out point by point here."""
    torch.manual_seed(0)
    coarse = grids.icosahedral(1)
    head = GravityHead(coarse, channels=3, hidden=4, num_basis=5, candidate_level=0).double()
    f = torch.randn(2, len(coarse), 3, dtype=torch.float64)
    mask = torch.rand(len(coarse)) < 0.6
    got = head(f, mask)["logits"]
    K, H = 5, 4
    w = coarse.area.double() * mask.double()
    W = head.field.weight.view(K, H, 3)
    c = head.field.bias.view(K, H)
    for b in range(2):
        for n, a in enumerate(grids.icosahedral(0).pos.double()):
            U = torch.zeros(H, dtype=torch.float64)
            for m, p in enumerate(coarse.pos.double()):
                theta = torch.arccos(torch.clamp(a @ p, -1, 1))
                for k in range(K):
                    phi = torch.exp(-0.5 * ((theta - k * math.pi / (K - 1)) / (math.pi / (K - 1))) ** 2)
                    U += w[m] / w.sum() * phi * (W[k] @ f[b, m] + c[k])
            want = head.score(torch.relu(U + head.bias))[0]
            torch.testing.assert_close(got[b, n], want, rtol=1e-10, atol=1e-12)
