"""The radial helpers every lens model with a polynomial shares: where a lens function
stops increasing, and its safeguarded inverse."""

import math

import numpy as np

from usf_graph.cameras.radial import from_incidence, incidence, monotone_limit, solve_monotone


def test_monotone_limit_finds_where_the_function_turns_back():
    # sin 3t rises until pi / 6, below 1 rad; t + t^3 never turns back
    assert abs(monotone_limit(lambda t: np.sin(3 * t), math.pi) - math.pi / 6) <= math.pi / 20000
    assert monotone_limit(lambda t: t + t ** 3, 2.0) == 2.0
    # flat is not increasing: a plateau from 0.5 on ends the range there
    assert abs(monotone_limit(lambda t: np.minimum(t, 0.5), 1.0) - 0.5) <= 1e-4


def test_solve_monotone_inverts_and_says_where_it_cannot():
    def g(t):
        return t + 0.3 * t ** 3

    def dg(t):
        return 1 + 0.9 * t ** 2

    hi = 1.5
    want = np.linspace(0.0, hi, 201)
    t, ok = solve_monotone(g, dg, g(want), hi)
    assert ok.all() and np.abs(t - want).max() < 1e-13
    # past g(hi), below g(0), NaN: not converged, never a wrong answer
    t, ok = solve_monotone(g, dg, np.array([g(hi) + 1e-6, -1e-6, np.nan, g(0.7)]), hi)
    assert ok.tolist() == [False, False, False, True] and abs(t[3] - 0.7) < 1e-13
    # any starting guess, even far outside [0, hi], converges to the same root
    t, ok = solve_monotone(g, dg, np.full(3, g(1.2)), hi, t0=[-5.0, 0.0, 9.0])
    assert ok.all() and np.abs(t - 1.2).max() < 1e-13


def test_incidence_and_from_incidence_are_inverse_past_ninety_degrees():
    theta = np.array([0.0, 0.3, math.pi / 2, 2.5, math.pi])
    phi = np.array([0.0, 1.0, -2.0, 3.0, 0.5])
    rays = from_incidence(theta, np.cos(phi), np.sin(phi))
    np.testing.assert_allclose(np.linalg.norm(rays, axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(incidence(rays), theta, atol=1e-15)
