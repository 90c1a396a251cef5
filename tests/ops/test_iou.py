import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from usf_graph.geometry import random_rotation
from usf_graph.grids import fibonacci
from usf_graph.ops import (
    box_area,
    box_iou,
    from_pandora,
    nms_keep,
    pairwise_box_iou,
    points_in_boxes,
    rotate_boxes,
    spherical_nms,
)
from usf_graph.ops import iou as iou_module
from usf_graph.ops.boxes import box_axes, box_planes, boxes_from_axes
from usf_graph.ops.iou import _caps_meet

F64 = torch.float64


def P(*b):
    """A box in PANDORA's degrees."""
    return from_pandora(np.array(b, np.float64))


def iou64(a, b):
    return float(box_iou(P(*a), P(*b), dtype=F64))


@pytest.mark.parametrize("fov, want", [((90, 90), 2 * math.pi / 3), ((60, 40), 0.687419),
                                       ((20, 20), 0.120633), ((180, 30), math.radians(60)),
                                       ((180, 100), math.radians(200))])
def test_area_closed_form(fov, want):
    assert float(box_area(P(0, 0, *fov, 0))) == pytest.approx(want, abs=5e-7)


@pytest.mark.parametrize("fov", [(200, 30), (30, -10)])
def test_area_refuses_a_field_of_view_outside_0_to_180_degrees(fov):
    with pytest.raises(ValueError, match=r"fields of view in \[0, 180\] degrees"):
        box_area(P(0, 0, *fov, 0))
    with pytest.raises(ValueError, match=r"fields of view in \[0, 180\] degrees"):
        box_area(torch.as_tensor(P(0, 0, *fov, 0)))


def test_area_matches_pandoras_formula():
    a, b = np.radians(70), np.radians(35)
    pandora = 4 * np.arccos(-np.sin(a / 2) * np.sin(b / 2)) - 2 * np.pi  # PANDORA's formula
    assert float(box_area([0, 0, a, b, 0])) == pytest.approx(pandora, rel=1e-12)


def test_published_iou_values():
    assert iou64((0, 0, 20, 20, 0), (0, 0, 20, 20, 0)) == pytest.approx(1, abs=1e-12)
    assert iou64((0, 0, 20, 20, 0), (20, 0, 20, 20, 0)) == pytest.approx(0, abs=1e-12)  # touching
    assert iou64((0, 0, 20, 20, 0), (0, 20, 20, 20, 0)) == pytest.approx(0, abs=1e-12)
    assert iou64((0, 0, 40, 40, 0), (0, 0, 20, 20, 0)) == pytest.approx(0.257222, abs=1e-6)  # nested
    assert iou64((0, 0, 20, 20, 0), (10, 0, 20, 20, 0)) == pytest.approx(0.33169, abs=1e-5)


@pytest.mark.parametrize("a, b", [
    ((179, 0, 20, 20, 0), (-179, 0, 20, 20, 0)),      # across the seam
    ((0, 85, 30, 30, 0), (180, 85, 30, 30, 0)),       # over the north pole
    ((0, -90, 30, 20, 0), (90, -90, 20, 30, 0)),      # at the south pole
    ((0, 0, 60, 20, 90), (0, 0, 20, 60, 0)),          # roll +90 = swapped fields of view
    ((0, 0, 60, 20, -90), (5, 3, 20, 60, 10)),        # roll -90
    ((30, 10, 50, 30, 35), (40, 20, 40, 40, -20)),
    ((0, 0, 20, 20, 0), (0, 0, 20, 20, 0)),           # identical
    ((100, 40, 10, 30, 45), (100, 40, 10, 30, 45)),
])
def test_iou_against_a_quadrature_reference(a, b):
    """Independent reference: area of the intersection by counting points of a dense
    Fibonacci grid inside both boxes."""
    pts = _dense()
    A, B = P(*a), P(*b)
    ina, inb = points_in_boxes(pts, A)[:, 0], points_in_boxes(pts, B)[:, 0]
    ref = (ina & inb).sum() / (ina | inb).sum()
    assert float(box_iou(A, B, dtype=F64)) == pytest.approx(ref, abs=2e-3)


_DENSE = {}


def _dense():
    if not _DENSE:
        _DENSE["p"] = fibonacci(2_000_000).pos.numpy()
    return _DENSE["p"]


def _random_boxes(n, seed, near=None):
    rng = np.random.default_rng(seed)
    lon = rng.uniform(-math.pi, math.pi, n)
    lat = np.arcsin(rng.uniform(-1, 1, n))
    b = np.stack([lon, lat, rng.uniform(0.05, 2.0, n), rng.uniform(0.05, 2.0, n),
                  rng.uniform(-math.pi / 2, math.pi / 2, n)], -1)
    if near is not None:  # partners close to the first boxes, so that most pairs overlap
        b[:, :2] = near[:, :2] + rng.normal(0, 0.3, (n, 2))
        b[:, 1] = np.clip(b[:, 1], -1.5, 1.5)
    return b


def test_iou_is_symmetric_rotation_invariant_and_fast_path_close():
    a = _random_boxes(500, 0)
    b = _random_boxes(500, 1, near=a)
    exact = box_iou(a, b, dtype=F64)
    assert (exact > 0.05).float().mean() > 0.4  # the test sees real overlaps
    torch.testing.assert_close(box_iou(b, a, dtype=F64), exact, atol=1e-10, rtol=0)
    R = random_rotation(seed=3).numpy()
    rot = box_iou(rotate_boxes(a, R), rotate_boxes(b, R), dtype=F64)
    torch.testing.assert_close(rot, exact, atol=1e-9, rtol=0)
    fast = box_iou(a, b, dtype=torch.float32).double()
    assert (fast - exact).abs().max() < 1e-4  # documented: float32 error on random pairs


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_iou_bounds_and_self_iou(seed):
    a = _random_boxes(20, seed)
    m = pairwise_box_iou(a, a, dtype=F64)
    assert ((m >= 0) & (m <= 1)).all()
    torch.testing.assert_close(m.diagonal(), torch.ones(20, dtype=F64), atol=1e-9, rtol=0)
    torch.testing.assert_close(m, m.T, atol=1e-10, rtol=0)


def test_iou_gradients_are_finite_and_match_differences():
    a = torch.tensor(P(10, 5, 40, 30, 20), requires_grad=True)
    b = torch.tensor(P(25, 12, 30, 40, -10))
    assert torch.autograd.gradcheck(lambda x: box_iou(x, b), (a,), eps=1e-7, atol=1e-6)
    same = torch.tensor(P(10, 5, 40, 30, 20), requires_grad=True)
    box_iou(same, b.new_tensor(P(10, 5, 40, 30, 20))).backward()
    assert torch.isfinite(same.grad).all()


def test_pairwise_matches_pairs_in_chunks():
    a, b = _random_boxes(30, 5), _random_boxes(40, 6)
    m = pairwise_box_iou(a, b, dtype=F64, chunk=100)
    want = torch.stack([box_iou(a[i], b, dtype=F64) for i in range(30)])
    torch.testing.assert_close(m, want, atol=1e-12, rtol=0)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), wide=st.booleans())
def test_pairwise_skips_only_pairs_that_share_no_point(seed, wide):
    """The pairs whose bounding caps are apart are set to 0 unclipped; clipping every pair
    (one broadcast :func:`box_iou`) gives the same matrix and the same gradients, for
    boxes of any size up to 179 degrees and pairs that nearly touch."""
    rng = np.random.default_rng(seed)
    a = _random_boxes(40, seed)
    b = np.concatenate([_random_boxes(20, seed + 1), _random_boxes(20, seed + 2, near=a[:20])])
    if wide:
        a[:10, 2:4] = rng.uniform(2.5, math.radians(179), (10, 2))
    # partners just past the far edge of a's first boxes, along their horizontal axis:
    # apart by 1e-6 rad, inside each other's caps
    c, e, _ = box_axes(a[:5])
    b[:5] = boxes_from_axes(np.cos(a[:5, 2:3] / 2 + 0.1 + 1e-6) * c
                            + np.sin(a[:5, 2:3] / 2 + 0.1 + 1e-6) * e, e, 0.2, 0.2)
    exact = None
    for dtype, tol in ((F64, 1e-12), (torch.float32, 1e-6)):
        x, y = torch.tensor(a, dtype=dtype, requires_grad=True), torch.tensor(b, dtype=dtype)
        fast = pairwise_box_iou(x, y)
        assert fast.dtype == dtype
        (g_fast,) = torch.autograd.grad((fast * torch.arange(40.0, dtype=dtype)).sum(), x)
        full = box_iou(x[:, None], y[None])
        (g_full,) = torch.autograd.grad((full * torch.arange(40.0, dtype=dtype)).sum(), x)
        torch.testing.assert_close(fast, full, atol=tol, rtol=0)
        torch.testing.assert_close(g_fast, g_full, atol=100 * tol, rtol=0)
        exact = full.detach() if exact is None else exact
    near = _caps_meet(torch.as_tensor(a), torch.as_tensor(b))
    assert 0 < int(near.sum()) < near.numel() and near[:5, :5].diagonal().all()
    assert (exact[~near] == 0).all() and (exact[:5, :5].diagonal() == 0).all()


def test_the_skipping_caps_pass_through_the_corners():
    """Each box's cap reaches exactly its farthest corner, so two boxes are skipped as
    soon as their centres are further apart than the two caps' radii: a looser cap would
    still be right, but would clip pairs for nothing (so this checks the radius itself)."""
    a, b = _random_boxes(30, 7), _random_boxes(30, 8)
    (ca, ea, _), (cb, eb, _) = box_axes(a), box_axes(b)
    ra = np.arccos(np.clip((box_planes(a)[1] * ca[:, None]).sum(-1), -1, 1)).max(1)
    rb = np.arccos(np.clip((box_planes(b)[1] * cb[:, None]).sum(-1), -1, 1)).max(1)
    for gap, meet in ((-1e-6, True), (1e-6, False)):
        # b's centre moved to ra + rb + gap from a's centre, along a's horizontal axis
        d = (ra + rb + gap)[:, None]
        moved = boxes_from_axes(np.cos(d) * ca + np.sin(d) * ea, eb, b[:, 2], b[:, 3])
        got = _caps_meet(torch.as_tensor(a), torch.as_tensor(moved)).diagonal()
        assert got.tolist() == [meet] * 30


@pytest.mark.parametrize("values", [True, False])
def test_pairwise_iou_of_no_boxes_has_the_other_side(values, monkeypatch):
    """Empty sides give empty matrices of the right shape, in eager mode and in the
    exporters' fixed-shape mode."""
    monkeypatch.setattr(iou_module, "check_values", lambda: values)
    some = torch.as_tensor(_random_boxes(3, 9))
    assert pairwise_box_iou(some[:0], some).shape == (0, 3)
    assert pairwise_box_iou(some, some[:0]).shape == (3, 0)
    far = some.clone()
    far[:, 0] += math.pi  # every pair apart: nothing clipped, all zeros
    far[:, 1] = -far[:, 1]
    far[:, 2:4] = 0.1
    near = some.clone()
    near[:, 2:4] = 0.1
    assert torch.equal(pairwise_box_iou(near, far), torch.zeros(3, 3, dtype=F64))


def test_nms_suppresses_only_iou_above_the_threshold():
    """As ``torchvision.ops.nms``: a box goes when its IoU with a better one is above the
    threshold, not at it; at a threshold of 0, boxes that only touch or are apart stay."""
    apart = np.array([P(0, 0, 20, 20, 0), P(20, 0, 20, 20, 0), P(90, 0, 20, 20, 0)])
    scores = torch.tensor([0.9, 0.8, 0.7])
    assert float(box_iou(apart[0], apart[1], dtype=F64)) < 1e-12  # they share an edge
    assert spherical_nms(apart, scores, 0.0).tolist() == [0, 1, 2]
    overlapping = np.array([P(0, 0, 20, 20, 0), P(19, 0, 20, 20, 0)])
    assert spherical_nms(overlapping, scores[:2], 0.0).tolist() == [0]


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_nms_keep_over_live_boxes_is_the_fixed_shape_nms(seed):
    """Eager NMS runs over the live boxes only; the exporters' form (every row, no value
    read) gives the same boxes, for live masks and classes that change between calls."""
    rng = np.random.default_rng(seed)
    first = _random_boxes(30, seed)
    boxes = torch.as_tensor(np.concatenate([first, _random_boxes(30, seed + 1, near=first)]))
    for _ in range(3):
        alive = torch.as_tensor(rng.random(60) < rng.uniform(0.1, 0.9))
        classes = torch.as_tensor(rng.integers(0, 3, 60))
        eager = nms_keep(boxes, alive, 0.3, classes)
        with pytest.MonkeyPatch.context() as m:
            m.setattr(iou_module, "check_values", lambda: False)
            fixed = nms_keep(boxes, alive, 0.3, classes)
        assert torch.equal(eager, fixed) and not (eager & ~alive).any()


def test_nms_keeps_the_best_of_each_cluster():
    boxes = np.array([P(0, 0, 20, 20, 0), P(2, 0, 20, 20, 0), P(179, 0, 20, 20, 0),
                      P(-178, 0, 20, 20, 0), P(60, 0, 20, 20, 0)])
    scores = torch.tensor([0.9, 0.95, 0.5, 0.8, 0.1])
    keep = spherical_nms(boxes, scores, 0.5)
    assert keep.tolist() == [1, 3, 4]  # 1 beats 0; 3 beats 2 across the seam


def _greedy(boxes, scores, thr, classes):
    """Greedy NMS as its definition reads, box by box in a Python list: the reference (the
    IoUs of every pair in one batched call: a call per pair took 9 s of the suite)."""
    iou = box_iou(boxes[:, None], boxes[None], dtype=F64).tolist()
    order = sorted(range(len(boxes)), key=lambda i: -scores[i])
    kept = []
    for i in order:
        if all(classes[j] != classes[i] or iou[i][j] <= thr for j in kept):
            kept.append(i)
    return kept


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 25), st.sampled_from([0.1, 0.3, 0.5]),
       st.integers(1, 3))
def test_nms_by_class_is_greedy_nms(seed, n, thr, num_classes):
    rng = np.random.default_rng(seed)
    first = _random_boxes(n, seed)
    boxes = np.concatenate([first, _random_boxes(n, seed + 1, near=first)])  # overlapping pairs
    scores = torch.as_tensor(rng.permutation(2 * n) / (2 * n))  # no ties: one greedy answer
    classes = torch.as_tensor(rng.integers(0, num_classes, 2 * n))
    keep = spherical_nms(boxes, scores, thr, classes=classes)
    assert keep.tolist() == _greedy(boxes, scores.tolist(), thr, classes.tolist())
    if num_classes == 1:  # classes that are all one are no classes
        assert keep.tolist() == spherical_nms(boxes, scores, thr).tolist()


def test_nms_keep_lets_only_live_boxes_suppress():
    boxes = torch.as_tensor(np.array([P(0, 0, 20, 20, 0), P(5, 0, 20, 20, 0), P(10, 0, 20, 20, 0)]))
    everyone = nms_keep(boxes, torch.ones(3, dtype=torch.bool), 0.5)
    assert everyone.tolist() == [True, False, True]  # 1 falls to 0, so 2 (far from 0) stays
    first_dead = nms_keep(boxes, torch.tensor([False, True, True]), 0.5)
    assert first_dead.tolist() == [False, True, False]  # a dead box suppresses nothing


def test_nms_refuses_scores_that_do_not_match_the_boxes():
    boxes = np.array([P(0, 0, 20, 20, 0), P(2, 0, 20, 20, 0)])
    with pytest.raises(ValueError, match=r"shape \[2\]"):
        spherical_nms(boxes, torch.tensor([0.9]), 0.5)
    with pytest.raises(ValueError, match="NaN"):
        spherical_nms(boxes, torch.tensor([0.9, float("nan")]), 0.5)


def test_bad_boxes():
    with pytest.raises(ValueError, match="180"):
        box_iou(P(0, 0, 180, 20, 0), P(0, 0, 20, 20, 0))
    with pytest.raises(ValueError, match="NaN"):
        box_iou([0, 0, float("nan"), 1, 0], [0, 0, 1, 1, 0])
