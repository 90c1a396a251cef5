"""A lens's per-pixel rays are computed once and kept: every later call, and every copy of
the camera mounted elsewhere, gets the same table as a fresh solve, and a change to the
lens (its parameters, size or field of view) gets its own."""

import math

import numpy as np
import pytest

from usf_graph import cameras as C
from usf_graph.cameras import kept
from usf_graph.geometry import random_rotation

LENSES = [
    C.Pinhole(60, 62, 40.2, 30.7, 80, 60, dist=(-0.3, 0.1, 1e-3, -1e-3, -0.02)),
    C.KannalaBrandt(40, 40, 40.2, 30.7, 80, 60, k=(0.02, -0.005, 0.001, -1e-4)),
    C.Mei(40, 40, 40.2, 30.7, 80, 60, xi=1.2, dist=(-0.1, 0.02, 0, 0)),
    C.DoubleSphere(40, 40, 40.2, 30.7, 80, 60, xi=-0.2, alpha=0.6),
    C.Scaramuzza([-30.0, 0.0, 4e-3], (30.7, 40.2), (1.0, 0.0, 0.0), 80, 60),
]


def _fresh(cam):
    return cam.unproject(cam.pixel_grid())


def _same(a, b):
    return np.array_equal(a[0], b[0], equal_nan=True) and np.array_equal(a[1], b[1])


@pytest.mark.parametrize("cam", LENSES, ids=lambda c: type(c).__name__)
def test_kept_rays_are_a_fresh_solves_for_every_copy_and_change(cam):
    kept.forget_rays()
    first = cam.pixel_rays()
    assert _same(first, _fresh(cam))
    first[0][:] = 0.0  # the caller's own copy: what is kept does not change
    first[1][:] = False
    again = cam.pixel_rays()
    assert _same(again, _fresh(cam)) and again[1].any()
    turned = cam.with_rotation(random_rotation(seed=3).numpy())
    assert _same(turned.pixel_rays(), again)  # the rays are the lens's, in its own frame
    narrower = cam.with_fov(0.8 * math.degrees(cam.max_incidence) * 2)
    rays, valid = narrower.pixel_rays()
    assert _same((rays, valid), _fresh(narrower)) and valid.sum() < again[1].sum()
    half = cam.resized(cam.width // 2, cam.height // 2)
    assert _same(half.pixel_rays(), _fresh(half)) and half.pixel_rays()[1].shape == (30, 40)
    assert _same(cam.pixel_rays(), _fresh(cam))  # still its own after the others


def test_other_parameters_are_another_lens():
    kept.forget_rays()
    a = C.KannalaBrandt(40, 40, 40.2, 30.7, 80, 60, k=(0.02, -0.005, 0.001, -1e-4))
    b = C.KannalaBrandt(40, 40, 40.2, 30.7, 80, 60, k=(0.03, -0.005, 0.001, -1e-4))
    a.pixel_rays()
    assert _same(b.pixel_rays(), _fresh(b)) and not _same(b.pixel_rays(), a.pixel_rays())


def test_the_budget_keeps_the_latest_and_skips_tables_too_large(monkeypatch):
    kept.forget_rays()
    built = []

    def table(n):
        built.append(n)
        return np.zeros((n, 3)), np.ones(n, bool)

    one = table(10)[0].nbytes + 10  # a table of 10 rays, in bytes
    built.clear()
    monkeypatch.setattr(kept, "BUDGET_BYTES", 4 * one)
    for key in "abcde":  # room for four: a goes
        kept.kept_rays(key, lambda: table(10))
    kept.kept_rays("b", lambda: table(10))
    kept.kept_rays("a", lambda: table(10))
    assert built == [10] * 6
    kept.kept_rays("b", lambda: table(10))  # used lately: kept when a came back
    assert built == [10] * 6
    for _ in range(2):  # more than a quarter of the budget: built each time
        kept.kept_rays("big", lambda: table(20))
    assert built == [10] * 6 + [20, 20]
