import math

import numpy as np
import pytest
import torch
from hypothesis import example, given, settings
from hypothesis import strategies as st

from usf_graph.cameras import Pinhole
from usf_graph.geometry import from_latlon, random_rotation
from usf_graph.grids import fibonacci
from usf_graph.ops import (
    box_area,
    box_axes,
    box_corners,
    box_edges,
    boxes_from_axes,
    canonical_boxes,
    fit_box,
    from_pandora,
    points_in_boxes,
    rotate_boxes,
    share_in_view,
    to_pandora,
)


def _same_box(a, b, tol):
    """Boxes as regions: equal corners up to the order a half turn gives."""
    ka, kb = box_corners(a), box_corners(b)
    return min(np.abs(ka - np.roll(kb, s, 0)).max() for s in (0, 2)) < tol


def test_frame_is_orthonormal_and_right_handed():
    c, e, n = box_axes([[0.3, -0.4, 0.5, 0.2, 0.7]])
    M = np.stack([c[0], e[0], n[0]])
    np.testing.assert_allclose(M @ M.T, np.eye(3), atol=1e-15)
    np.testing.assert_allclose(np.cross(c[0], e[0]), n[0], atol=1e-15)


def test_roll_zero_axes_are_east_and_north():
    c, e, n = box_axes([0.0, 0.0, 0.5, 0.5, 0.0])
    np.testing.assert_allclose(c, [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(e, [0, 1, 0], atol=1e-15)  # east = increasing longitude = +y
    np.testing.assert_allclose(n, [0, 0, 1], atol=1e-15)


def test_sign_of_roll_in_pandora_terms():
    # DESIGN.md: PANDORA [0,0,60,20,30] contains (lon 22, lat 12) and not (22, -12), in its
    # own coordinates, where longitude grows to the right of the image.
    box = from_pandora([0, 0, 60, 20, 30])
    inside = from_latlon(math.radians(12), -math.radians(22))  # our lon is PANDORA's negative
    outside = from_latlon(-math.radians(12), -math.radians(22))
    assert points_in_boxes(inside, box)[0, 0]
    assert not points_in_boxes(outside, box)[0, 0]


def test_pandora_round_trip():
    b = np.array([[170, 20, 30, 20, 45], [-179.5, -89, 10, 100, -90.0 + 1e-9], [0, 0, 1, 1, 0]])
    np.testing.assert_allclose(to_pandora(from_pandora(b)), b, atol=1e-9)


def test_canonical_boxes_are_the_same_regions_with_a_small_roll():
    rng = np.random.default_rng(3)
    b = np.c_[rng.uniform(-np.pi, np.pi, 200), rng.uniform(-1.4, 1.4, 200),
              rng.uniform(0.1, 2.0, (200, 2)), rng.uniform(-3 * np.pi, 3 * np.pi, 200)]
    c = canonical_boxes(b)
    assert (np.abs(c[:, 4]) <= np.pi / 4 + 1e-12).all()
    p = from_latlon(torch.as_tensor(rng.uniform(-1.5, 1.5, 4000)),
                    torch.as_tensor(rng.uniform(-np.pi, np.pi, 4000))).numpy()
    assert np.array_equal(points_in_boxes(p, b), points_in_boxes(p, c))  # the same directions
    assert points_in_boxes(p, b).any(0).all()
    # a tall box at roll 80 degrees is a wide one at -10: widths swapped
    np.testing.assert_allclose(canonical_boxes([0.1, 0.2, 0.3, 0.9, math.radians(80)]),
                               [0.1, 0.2, 0.9, 0.3, math.radians(-10)], atol=1e-12)
    np.testing.assert_allclose(canonical_boxes(c), c, atol=1e-12)


def test_points_in_box_edges_are_great_circles():
    b = np.array([0.4, 0.3, 1.0, 0.6, 0.2])
    edge = box_edges(b, 50)[:-1]
    c, _, _ = box_axes(b)
    inward = (edge + 1e-7 * c) / np.linalg.norm(edge + 1e-7 * c, axis=-1, keepdims=True)
    outward = (edge - 1e-7 * c) / np.linalg.norm(edge - 1e-7 * c, axis=-1, keepdims=True)
    assert points_in_boxes(inward, b).all()
    assert not points_in_boxes(outward, b).any()


@settings(max_examples=40, deadline=None)
@given(lon=st.floats(-math.pi, math.pi), lat=st.floats(-1.5, 1.5),
       roll=st.floats(-1.5, 1.5), along=st.floats(-3.0, 3.0), scale=st.floats(0.1, 10.0))
def test_a_box_from_its_axes_takes_the_horizontal_axis_projected_to_its_tangent_plane(
        lon, lat, roll, along, scale):
    b = np.array([lon, lat, 0.5, 0.3, roll])
    c, e, _ = box_axes(b)
    back = boxes_from_axes(c, scale * e + along * c, 0.5, 0.3)  # any length, off the plane
    assert _same_box(back, b, 1e-9) and -math.pi / 2 <= back[4] < math.pi / 2


@settings(max_examples=40, deadline=None)
@given(lon=st.floats(-math.pi, math.pi), lat=st.floats(-1.55, 1.55),
       fx=st.floats(0.02, 2.6), fy=st.floats(0.02, 2.6), seed=st.integers(0, 10_000))
def test_rotation_is_exact(lon, lat, fx, fy, seed):
    b = np.array([lon, lat, fx, fy, 0.3])
    R = random_rotation(seed=seed).numpy()
    got, want = box_corners(rotate_boxes(b, R)), box_corners(b) @ R.T
    assert min(np.abs(got - np.roll(want, s, 0)).max() for s in (0, 2)) < 1e-12
    p = np.random.default_rng(seed).normal(size=(200, 3))
    assert np.array_equal(points_in_boxes(p, b), points_in_boxes(p @ R.T, rotate_boxes(b, R)))


@settings(max_examples=60, deadline=None)
@given(lon=st.floats(-math.pi, math.pi), lat=st.floats(-1.5707, 1.5707),
       fx=st.floats(0.01, 2.6), fy=st.floats(0.01, 2.6), seed=st.integers(0, 10_000),
       tilted=st.booleans())
@example(lon=0.0, lat=-0.96875, fx=1.375, fy=2.5390625, seed=0, tilted=False)  # holds the nadir
def test_fit_recovers_a_box_from_its_outline(lon, lat, fx, fy, seed, tilted):
    b = np.array([lon, lat, fx, fy, 0.0])
    up = np.array([0.0, 0.0, 1.0])
    if tilted:  # a box with roll 0 in a tilted frame is up-aligned with that frame's up
        R = random_rotation(seed=seed).numpy()
        b, up = rotate_boxes(b, R), R[:, 2]
    outline = box_edges(b, 40)
    fit = fit_box(outline, up=up)
    assert fit is not None
    if not points_in_boxes(np.stack([up, -up]), b).any():
        assert _same_box(fit, b, 1e-8)
    else:  # around up or down, roll 0 turns with the centre: other tight up-aligned boxes exist
        inward = outline + 1e-7 * box_axes(b)[0]
        assert points_in_boxes(inward / np.linalg.norm(inward, axis=-1, keepdims=True), fit).all()
        assert box_area(torch.as_tensor(fit)) <= 1.05 * box_area(torch.as_tensor(b))


def test_fit_around_up_is_not_unique_but_tight():
    """A box over the pole (found by hypothesis): the fit is another tight up-aligned box."""
    b = np.array([0.0, 1.5625, 2.5, 1.0, 0.0])
    fit = fit_box(box_edges(b, 40))
    assert not _same_box(fit, b, 1e-3)  # a different box, 0.5 degree away, axes swapped
    assert abs(fit[2] - b[3]) < 0.03 and abs(fit[3] - b[2]) < 0.01
    assert box_area(torch.as_tensor(fit)) <= 1.05 * box_area(torch.as_tensor(b))


def test_fit_is_tight_and_contains_random_points():
    rng = np.random.default_rng(0)
    d = rng.normal(size=(500, 3)) * [0.3, 0.3, 0.2] + [3, 1, 0.5]
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    b = fit_box(d)
    assert abs(b[4]) < 1e-12
    assert points_in_boxes(d, b).all()
    for side in range(4):  # moving any one side in by 1e-6 rad leaves a point out
        c, e, n = box_axes(b)
        x, y, z = d @ e, d @ n, d @ c
        u = (x, -x, y, -y)[side] / z
        half = b[2 + side // 2] / 2
        assert u.max() > math.tan(half - 1e-6)


def test_fit_rejects_directions_around_the_viewpoint():
    ring = from_latlon(np.zeros(12), np.linspace(-math.pi, math.pi, 12, endpoint=False))
    assert fit_box(ring) is None


def test_bad_boxes_raise():
    with pytest.raises(ValueError, match=r"\[\.\.\., 5\]"):
        box_axes([1, 2, 3])
    with pytest.raises(ValueError, match="NaN"):
        rotate_boxes([0, 0, np.nan, 1, 0], np.eye(3))
    with pytest.raises(ValueError, match="NaN"):
        points_in_boxes([[np.nan, 0, 1]], [0, 0, 1, 1, 0])


@pytest.mark.parametrize("R, what", [
    (2 * np.eye(3), "not a rotation"), (np.diag([1.0, 1.0, -1.0]), "not a rotation"),
    (np.full((3, 3), np.nan), "NaN"), (np.eye(4), "3x3")])
def test_rotate_boxes_refuses_what_is_not_a_rotation(R, what):
    b = np.array([[0.1, 0.2, 0.3, 0.4, 0.5], [1.0, -0.5, 0.2, 0.6, -0.3]])
    with pytest.raises(ValueError, match=what):
        rotate_boxes(b, R)


def test_box_ops_take_tensors_as_they_take_arrays():
    b = np.array([[0.1, 0.2, 0.3, 0.4, 0.5], [3.0, -0.5, 0.2, 0.6, -0.3]])
    R = random_rotation(seed=3)
    got = rotate_boxes(torch.as_tensor(b), R)
    assert np.abs(got - rotate_boxes(b, R.numpy())).max() < 1e-12
    p = np.random.default_rng(0).normal(size=(500, 3))
    inside = points_in_boxes(torch.as_tensor(p), torch.as_tensor(b))
    assert np.array_equal(inside, points_in_boxes(p, b)) and inside.any()


def test_share_in_view_exact_cases_and_a_dense_reference():
    boxes = from_pandora(np.array([[0, 0, 30, 20, 25], [40, -10, 60, 100, -70], [-55, 35, 50, 40, 30],
                                   [170, 30, 150, 80, 10]], np.float64))
    assert np.allclose(share_in_view(boxes, lambda d: np.ones(len(d), bool)), 1.0)
    assert np.allclose(share_in_view(boxes, lambda d: np.zeros(len(d), bool)), 0.0)
    # a box centred on the equator is symmetric under the half turn about its centre,
    # which swaps the two hemispheres: exactly half of it above the horizon
    assert share_in_view(boxes[:1], lambda d: d[:, 2] > 0)[0] == pytest.approx(0.5, abs=1e-12)
    # a real lens (a 116-degree pinhole looking along +x), against the share of a dense
    # Fibonacci set of directions: inside, cut twice, behind it
    cam = Pinhole(30.0, 30.0, 47.5, 47.5, 96, 96)
    pts = fibonacci(400_000).pos.double().numpy()
    inside = points_in_boxes(pts, boxes)
    _, seen = cam.sees(pts)
    want = [seen[inside[:, k]].mean() for k in range(len(boxes))]
    got = share_in_view(boxes, lambda d: cam.sees(d)[1], n=128)
    assert want[0] == 1 and 0.1 < want[1] < 0.9 and 0.1 < want[2] < 0.9 and want[3] == 0
    assert np.allclose(got, want, atol=2e-3)


def test_planes_and_corners_bound_the_same_directions_as_points_in_boxes():
    """A direction is inside a box exactly where it is on the inner side of the box's four
    great circles; each corner is a unit direction on the two circles that meet there."""
    from usf_graph.ops import box_planes

    rng = np.random.default_rng(5)
    b = np.c_[rng.uniform(-np.pi, np.pi, 50), rng.uniform(-1.4, 1.4, 50),
              rng.uniform(0.2, 2.8, (50, 2)), rng.uniform(-np.pi, np.pi, 50)]
    p = rng.normal(size=(20_000, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    planes, corners = box_planes(b)
    side = np.einsum("pd,bkd->pbk", p, planes)
    clear = np.abs(side).min(-1) > 1e-9  # off the borders, where rounding decides
    assert np.array_equal((side >= 0).all(-1)[clear], points_in_boxes(p, b)[clear])
    assert points_in_boxes(p, b).sum(0).min() > 0
    np.testing.assert_allclose(np.linalg.norm(corners, axis=-1), 1.0, rtol=0, atol=1e-15)
    on = np.abs(np.einsum("bkd,bjd->bkj", corners, planes)) < 1e-12  # corner k on circle j
    meet = [(0, 2), (0, 3), (1, 3), (1, 2)]  # (+e, +n), (+e, -n), (-e, -n), (-e, +n)
    for k, (i, j) in enumerate(meet):
        assert on[:, k, i].all() and on[:, k, j].all() and on[:, k].sum(-1).max() == 2


def test_a_box_of_half_the_sphere_or_more_holds_the_front_half():
    """Past 180 degrees the tangent plane has no edge: such a field of view holds every
    direction in front of the centre within the other field of view."""
    for fx in (math.pi, math.radians(200)):
        b = [0.0, 0.0, fx, 0.4, 0.0]
        near_side = from_latlon(np.zeros(3), np.radians([89.0, -89.0, 0.0]))
        assert points_in_boxes(near_side, b)[:, 0].all()
        behind = from_latlon(0.0, math.radians(91.0))
        assert not points_in_boxes(behind, b)[0, 0]


def test_fit_keeps_the_whole_hull_of_a_lopsided_cloud():
    """Directions filling a triangle far from their mean: the extremes seen from the
    starting centre are not those at the answer, so the fit needs every hull vertex. The
    box holds every direction and each side touches one."""
    rng = np.random.default_rng(2)
    a, b2 = rng.uniform(size=(2, 3000))
    keep = a + b2 < 1
    x, y = 0.9 * a[keep] ** 3 - 0.1, 0.7 * b2[keep] - 0.2  # dense at one corner, a long tail
    d = np.stack([np.ones_like(x), x, y], -1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    fit = fit_box(d)
    assert points_in_boxes(d, fit, margin=1e-9).all()
    c, e, n = box_axes(fit)
    u, v = d @ e / (d @ c), d @ n / (d @ c)
    for got, half in ((u.max(), fit[2] / 2), (-u.min(), fit[2] / 2), (v.max(), fit[3] / 2),
                      (-v.min(), fit[3] / 2)):
        assert got == pytest.approx(math.tan(half), abs=1e-9)
