"""SphericalClassifier: exact invariance under the grid's symmetries, options, errors."""

import math

import numpy as np
import pytest
import torch

from usf_graph import grids
from usf_graph.geometry import rotation_from_axis_angle
from usf_graph.models import SphericalClassifier
from usf_graph.testing import symmetry_permutation


@pytest.mark.parametrize("readout", ["meanpow", "meanmax", "mean"])
def test_classifier_is_exactly_invariant_under_the_icosahedral_group(readout, pool="gaussian"):
    # (cluster pooling is not: icosahedral midpoints tie between two coarse points)
    torch.manual_seed(1)
    m = SphericalClassifier(level=3, channels=(4, 6, 8), pool=pool, readout=readout).double()
    m.eval()
    assert len(m.pairs) == 2  # the gradient pairs after the first two stages are covered
    pos = grids.icosahedral(3).pos
    axis = pos[0] / pos[0].norm()  # a vertex of the icosahedron: a 5-fold axis
    R = rotation_from_axis_angle(axis, torch.tensor(2 * np.pi / 5, dtype=torch.float64))
    sigma = symmetry_permutation(pos, R)  # raises unless R maps the grid onto itself
    x = torch.randn(2, len(pos), 1, dtype=torch.float64)
    xr = torch.empty_like(x)
    xr[:, sigma] = x  # the rotated signal
    with torch.no_grad():
        y, yr, y2 = m(x), m(xr), m(torch.roll(x, 1, 1))
    assert (y - yr).abs().max() < 1e-10
    assert (y - y2).abs().max() > 1e-7  # another signal: the logits are not constant


def test_classifier_options_and_bad_arguments():
    m = SphericalClassifier(level=3, channels=(4, 6, 8), input_level=4, min_level=2)
    assert len(m.pools) == 1 and m.input_pool is not None  # 4 -> 3 (input), 3 -> 2, stay
    assert m(torch.randn(2, len(grids.icosahedral(4).pos), 1)).shape == (2, 10)
    for x, match in ((torch.randn(2, 642, 1), r"expected x \[B, 2562, 1\]"),
                     (torch.randn(2, 2562, 3), "1 channel"),
                     (torch.full((2, 2562, 1), float("nan")), "NaN")):
        with pytest.raises(ValueError, match=match):
            m(x)
    for bad, match in ((dict(readout="max"), "readout"), (dict(pool="avg"), "pool"),
                       (dict(min_level=4), "min_level"), (dict(input_level=2), "input_level"),
                       (dict(input_level=4, jet_spacings=None), "input_level"),
                       (dict(pairs=-1), "pairs"), (dict(jet_spacings=None), "gradient pairs")):
        with pytest.raises(ValueError, match=match):
            SphericalClassifier(level=3, channels=(4, 6), **bad)


def test_classifier_is_built_as_its_docstring_says():
    """Stage s convolves with radius radius_spacings grid spacings on level - s, down to
    min_level (0 allowed); pooling blurs by pool_sigma coarse spacings; gradient pairs
    follow the first pair_stages stages, never the last; pairs=0 or pair_stages=0: none."""
    m = SphericalClassifier(level=3, channels=(4, 6, 8), pool_sigma=0.7, radius_spacings=2.5,
                            pairs=2, pair_stages=5)
    spacing = {lv: float(grids.icosahedral(lv).spacing) for lv in range(4)}
    assert [c.radius for c in m.convs] == pytest.approx([2.5 * spacing[lv] for lv in (3, 2, 1)])
    assert [p.sigma for p in m.pools] == pytest.approx([0.7 * spacing[2], 0.7 * spacing[1]])
    assert len(m.pairs) == 2
    bottom = SphericalClassifier(level=2, channels=(4, 6, 8, 8), min_level=0, pairs=0)
    assert len(bottom.pools) == 2 and len(bottom.pairs) == 0
    assert bottom(torch.randn(1, len(grids.icosahedral(2).pos), 1)).shape == (1, 10)
    # on level 0 (12 points, 63 degrees apart) a kernel of 3 spacings is the whole sphere
    assert bottom.convs[-1].radius == pytest.approx(math.pi)
    coarse = SphericalClassifier(level=1, channels=(4, 6), min_level=0, pairs=2).eval()
    assert len(coarse.pairs) == 1 and torch.isfinite(coarse(torch.randn(2, 42, 1))).all()
    assert len(SphericalClassifier(level=2, channels=(4, 6), pairs=2, pair_stages=0).pairs) == 0


def test_readouts_are_the_documented_integrals_and_one_sample_reads_alone():
    """meanpow reads the area-weighted mean and (int x^4)^(1/4) of the last stage's
    features, meanmax the mean and the max; a single sample [N, C] reads as a batch of
    one. Pooling stops after the last stage even when min_level lies further down."""
    torch.manual_seed(2)
    m = SphericalClassifier(level=3, channels=(4, 6), min_level=1).double().eval()
    assert len(m.pools) == 1
    x = torch.randn(2, len(grids.icosahedral(3).pos), 1, dtype=torch.float64)
    last = []
    hook = m.norms[-1].register_forward_hook(lambda mod, i, o: last.append(torch.relu(o)))
    with torch.no_grad():
        f = m.features(x)
        m.readout = "meanmax"
        g = m.features(x)
    hook.remove()
    a = grids.icosahedral(2).area.double()[None, :, None]
    y = last[0]
    mean = (a * y).sum(1) / a.sum()
    torch.testing.assert_close(f, torch.cat([mean, ((a * y ** 4).sum(1) / a.sum() + 1e-6) ** 0.25], -1))
    torch.testing.assert_close(g, torch.cat([mean, y.amax(1)], -1))
    with torch.no_grad():
        torch.testing.assert_close(m(x[1]), m(x)[1])
