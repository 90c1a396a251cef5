"""SphericalClassifier: exact invariance under the grid's symmetries, options, errors."""


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
