import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from usf_graph import geometry as G

unit = st.tuples(*[st.floats(-1, 1) for _ in range(3)]).filter(
    lambda v: 1e-3 < math.sqrt(sum(c * c for c in v))).map(lambda v: G.normalize(np.array(v)))


@given(unit)
def test_latlon_roundtrip_numpy(p):
    lat, lon = G.to_latlon(p)
    assert -math.pi / 2 <= lat <= math.pi / 2 and -math.pi <= lon < math.pi
    np.testing.assert_allclose(G.from_latlon(lat, lon), p, atol=1e-12)


def test_latlon_roundtrip_torch_and_convention():
    lat = torch.tensor([0.0, 0.0, math.pi / 2, 0.3], dtype=torch.float64)
    lon = torch.tensor([0.0, math.pi / 2, 0.0, -2.0], dtype=torch.float64)
    p = G.from_latlon(lat, lon)
    torch.testing.assert_close(p[0], torch.tensor([1.0, 0, 0], dtype=torch.float64))  # forward
    torch.testing.assert_close(p[1], torch.tensor([0.0, 1, 0], dtype=torch.float64), atol=1e-15, rtol=0)
    torch.testing.assert_close(p[2], torch.tensor([0.0, 0, 1], dtype=torch.float64), atol=1e-15, rtol=0)
    lat2, lon2 = G.to_latlon(p)
    torch.testing.assert_close(lat2[[0, 1, 3]], lat[[0, 1, 3]])
    torch.testing.assert_close(lon2[[0, 1, 3]], lon[[0, 1, 3]])
    # lon = pi maps to -pi (half-open range)
    _, l = G.to_latlon(np.array([-1.0, 0.0, 0.0]))
    assert l == -math.pi
    _, lt = G.to_latlon(torch.tensor([-1.0, 0.0, 0.0], dtype=torch.float64))
    assert lt.item() == -math.pi  # in torch too


@given(unit, unit, unit)
def test_distance_metric_axioms(p, q, r):
    d = G.geodesic_distance
    assert d(p, q) == pytest.approx(d(q, p), abs=1e-15)
    assert d(p, r) <= d(p, q) + d(q, r) + 1e-12
    assert d(p, -p) == pytest.approx(math.pi, abs=1e-12)
    assert d(p, p) == pytest.approx(0.0, abs=1e-12)
    assert 0 <= d(p, q) <= math.pi


def test_distance_is_accurate_for_tiny_angles():
    eps = 1e-9
    p = np.array([1.0, 0, 0])
    q = np.array([math.cos(eps), math.sin(eps), 0])
    assert G.geodesic_distance(p, q) == pytest.approx(eps, rel=1e-9)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_distance_gradient_finite_at_0_and_pi(sign):
    p = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
    p = p / p.norm()
    q = (sign * p).clone().requires_grad_(True)
    pp = p.clone().requires_grad_(True)
    d = G.geodesic_distance(pp, q)
    d.backward()
    assert torch.isfinite(pp.grad).all() and torch.isfinite(q.grad).all()
    assert d.item() == pytest.approx(0.0 if sign > 0 else math.pi, abs=1e-12)


def test_random_rotations_are_proper_and_seeded():
    R = G.random_rotation(1000, seed=3)
    eye = torch.eye(3, dtype=torch.float64).expand(1000, 3, 3)
    torch.testing.assert_close(R @ R.transpose(1, 2), eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(1000, dtype=torch.float64))
    torch.testing.assert_close(R, G.random_rotation(1000, seed=3), rtol=0, atol=0)
    g = torch.Generator().manual_seed(3)
    torch.testing.assert_close(R, G.random_rotation(1000, generator=g), rtol=0, atol=0)
    assert not torch.equal(R, G.random_rotation(1000, seed=4))


def test_rotations_are_haar_uniform():
    R = G.random_rotation(20000, seed=0)
    # Haar: the rotation angle w has density (1 - cos w) / pi, CDF (w - sin w) / pi.
    w = G.rotation_angle(R).numpy()
    assert stats.kstest(w, lambda x: (x - np.sin(x)) / np.pi).pvalue > 1e-3
    # ... and R z is uniform on S2: its z-component is uniform on [-1, 1].
    assert stats.kstest(R[:, 2, 2].numpy(), "uniform", args=(-1, 2)).pvalue > 1e-3
    # The check can fail: a biased sampler (uniform Euler angles) is rejected.
    a = torch.rand(20000, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    z = torch.tensor([0.0, 0, 1], dtype=torch.float64)
    x = torch.tensor([1.0, 0, 0], dtype=torch.float64)
    bad = (G.rotation_from_axis_angle(z.expand(20000, 3), a[:, 0] * 2 * math.pi)
           @ G.rotation_from_axis_angle(x.expand(20000, 3), a[:, 1] * math.pi))
    assert stats.kstest(bad[:, 2, 2].numpy(), "uniform", args=(-1, 2)).pvalue < 1e-6


def test_axis_angle_and_quaternion_agree_and_rotate():
    R = G.rotation_from_axis_angle(np.array([0, 0, 1.0]), math.pi / 2)
    np.testing.assert_allclose(G.rotate(np.array([[1.0, 0, 0]]), R), [[0, 1, 0]], atol=1e-15)
    q = np.array([math.cos(0.35), 0, math.sin(0.35), 0])  # 0.7 rad about y
    np.testing.assert_allclose(G.rotation_from_quaternion(q),
                               G.rotation_from_axis_angle([0, 2.0, 0], 0.7), atol=1e-15)
    assert G.rotation_angle(R) == pytest.approx(math.pi / 2)
    Rt = G.rotation_from_axis_angle(torch.tensor([1.0, 1, 0]), torch.tensor(2.5))
    assert G.rotation_angle(Rt).item() == pytest.approx(2.5)
    # rotation preserves geodesic distance
    p, q = G.normalize(np.random.default_rng(0).normal(size=(2, 10, 3)))
    np.testing.assert_allclose(G.geodesic_distance(G.rotate(p, R), G.rotate(q, R)),
                               G.geodesic_distance(p, q), atol=1e-14)


@settings(max_examples=50)
@given(st.floats(0.0, 1.0))
def test_chord_geodesic_roundtrip(t):
    d = t * math.pi
    # the chord 2 sin(d/2) flattens at d = pi, so d is only determined to eps / cos(d/2)
    tol = 1e-12 + 1e-15 / max(math.cos(d / 2), 1e-8)
    assert G.chord_to_geodesic(G.geodesic_to_chord(d)) == pytest.approx(d, abs=tol)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_chord_geodesic_torch_matches_numpy_with_gradients(seed):
    d = torch.rand(7, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    d = (d * 3.0).requires_grad_()  # below pi, where the inverse's gradient is finite
    c = G.geodesic_to_chord(d)
    np.testing.assert_allclose(c.detach().numpy(), 2 * np.sin(d.detach().numpy() / 2), rtol=1e-15)
    back = G.chord_to_geodesic(c)
    np.testing.assert_allclose(back.detach().numpy(), G.chord_to_geodesic(c.detach().numpy()),
                               rtol=1e-15)
    np.testing.assert_allclose(back.detach().numpy(), d.detach().numpy(), rtol=1e-12)
    back.sum().backward()
    np.testing.assert_allclose(d.grad.numpy(), 1.0, rtol=1e-9)  # the round trip is the identity
    # a chord past 2 by rounding is the antipode, not NaN
    assert G.chord_to_geodesic(2 + 4e-16) == math.pi
    assert G.chord_to_geodesic(torch.tensor(2 + 4e-16, dtype=torch.float64)).item() == math.pi


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_tangent_towards_is_the_log_maps_direction_row_by_row(seed):
    gen = torch.Generator().manual_seed(seed)
    p = G.normalize(torch.randn(2, 3, 3, generator=gen, dtype=torch.float64))  # any leading shape
    q = G.normalize(torch.randn(2, 3, 3, generator=gen, dtype=torch.float64))
    t = G.tangent_towards(p, q)
    for pi, qi, ti in zip(p.reshape(-1, 3).numpy(), q.reshape(-1, 3).numpy(), t.reshape(-1, 3).numpy()):
        # the great circle through p and q: its unit tangent at p, computed here by angles
        d = float(G.geodesic_distance(pi, qi))
        want = (qi - np.cos(d) * pi) / np.sin(d)
        np.testing.assert_allclose(ti, want, atol=1e-12)


def test_tangent_towards_points_along_the_great_circle():
    tangent_towards = G.tangent_towards
    p = torch.tensor([[0.0, 0, 1], [1.0, 0, 0]], dtype=torch.float64)
    q = torch.tensor([[0.6, 0.8, 0], [0.0, 0.6, 0.8]], dtype=torch.float64)
    want = torch.tensor([[0.6, 0.8, 0], [0.0, 0.6, 0.8]], dtype=torch.float64)
    assert (tangent_towards(p, q) - want).abs().max() < 1e-15
    near = torch.tensor([[0.0, 0.1, 1.0]], dtype=torch.float64)
    near = near / near.norm()
    assert (tangent_towards(p[:1], near) - torch.tensor([[0.0, 1, 0]])).abs().max() < 1e-12
    assert (tangent_towards(p, p) == 0).all()  # no direction where q = p


@settings(max_examples=200, deadline=None)
@given(unit)
def test_level_rotation_turns_up_to_z_about_a_horizontal_axis(u):
    """The smallest turn: a proper rotation taking ``u`` to +z by the angle between them,
    about an axis orthogonal to both (so it adds no turn about up: no change of heading)."""
    R = G.level_rotation(u * 3.0)  # any length
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(R @ u, [0.0, 0.0, 1.0], atol=1e-12)
    assert np.isclose(G.rotation_angle(R), math.acos(np.clip(u[2], -1, 1)), atol=1e-7)
    axis = np.cross(u, [0.0, 0.0, 1.0])
    if np.linalg.norm(axis) > 1e-6:
        assert np.allclose(R @ axis, axis, atol=1e-12)


def test_level_rotation_at_the_poles_and_on_bad_input():
    assert np.array_equal(G.level_rotation([0.0, 0.0, 2.0]), np.eye(3))
    R = G.level_rotation([0.0, 0.0, -1.0])
    assert np.allclose(R @ [0.0, 0.0, -1.0], [0.0, 0.0, 1.0]) and np.isclose(np.linalg.det(R), 1.0)
    for bad in ([0.0, 0.0, 0.0], [np.nan, 0.0, 1.0], [1.0, 2.0]):
        with pytest.raises(ValueError, match="finite, non-zero 3-vector"):
            G.level_rotation(bad)


def test_as_rotation_matrix_refuses_what_is_not_a_rotation():
    R = G.random_rotation(seed=4)
    np.testing.assert_array_equal(G.as_rotation_matrix(R), R.numpy())  # a tensor is taken
    for nudged in (R.numpy() + 1e-8, R.numpy() * (1 - 1e-8)):  # within the tolerance, det < 1
        np.testing.assert_array_equal(G.as_rotation_matrix(nudged), nudged)
    with pytest.raises(ValueError, match=r"R must be a 3x3 rotation matrix, got shape \(2, 3, 3\)"):
        G.as_rotation_matrix(np.stack([np.eye(3)] * 2))
    with pytest.raises(ValueError, match="Q contains NaN"):
        G.as_rotation_matrix(np.where(np.eye(3) > 0, np.nan, 0.0), name="Q")
    for bad in (np.diag([1.0, 1.0, -1.0]), 1.01 * np.eye(3), np.eye(3) + 1e-5):
        with pytest.raises(ValueError, match="is not a rotation matrix"):
            G.as_rotation_matrix(bad)


def test_rotation_angle_of_batches_in_numpy_and_torch():
    angles = np.array([0.0, 0.3, 1.7, np.pi])
    axes = G.normalize(np.array([[1.0, 2, 3], [0, 0, 1], [-1, 0.5, 0], [0.3, -0.2, 0.9]]))
    R = G.rotation_from_axis_angle(axes, angles)
    np.testing.assert_allclose(G.rotation_angle(R), angles, atol=1e-7)
    np.testing.assert_allclose(G.rotation_angle(torch.as_tensor(R)).numpy(), angles, atol=1e-7)
    # a tensor angle about a numpy axis gives tensors
    Rt = G.rotation_from_axis_angle(axes, torch.as_tensor(angles))
    assert torch.is_tensor(Rt)
    np.testing.assert_allclose(Rt.numpy(), R, atol=1e-15)


def test_rotate_takes_torch_when_either_input_is_torch():
    """Points and rotation of mixed kinds give a tensor in the points' dtype, R p."""
    R = G.rotation_from_axis_angle(np.array([0.0, 0.0, 1.0]), math.pi / 2)
    p = np.array([[1.0, 0.0, 0.0]])
    for pts, rot in ((p, torch.as_tensor(R)), (torch.as_tensor(p, dtype=torch.float32), R)):
        out = G.rotate(pts, rot)
        assert torch.is_tensor(out) and out.dtype == torch.as_tensor(pts).dtype
        torch.testing.assert_close(out, torch.tensor([[0.0, 1.0, 0.0]], dtype=out.dtype),
                                   atol=1e-7, rtol=0)
