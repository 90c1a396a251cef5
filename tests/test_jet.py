"""LocalJet: exact rotation invariance and the analytic jet of f = z."""

import pytest
import torch

from usf_graph import grids
from usf_graph.geometry import normalize, random_rotation, rotate
from usf_graph.nn import LocalJet, geodesic_radius_graph


def _jet(pos, radius, h):
    ei, ew = geodesic_radius_graph(pos, radius)
    return LocalJet(pos, ei, ew, h)


def test_invariants_are_exactly_rotation_invariant():
    pos = normalize(torch.randn(400, 3, dtype=torch.float64,
                                generator=torch.Generator().manual_seed(0)))
    x = torch.randn(2, 400, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    y = _jet(pos, 0.5, 0.1)(x)
    assert y.shape == (2, 400, 12)
    assert torch.equal(y[..., :3], x)
    for seed in range(3):
        R = random_rotation(seed=seed).double()
        yr = _jet(rotate(pos, R), 0.5, 0.1)(x)  # new graph, new tangent frames
        assert (yr - y).abs().max() < 1e-10
    assert (y[..., 3:] - _jet(pos, 0.5, 0.1)(x.flip(1))[..., 3:]).abs().max() > 1e-2


def test_jet_of_z_matches_the_analytic_invariants():
    # f = z: surface gradient sqrt(1 - z^2), Hess f = -f I, so Laplacian -2z and det z^2
    g = grids.icosahedral(5)
    h = g.spacing
    z = g.pos[:, 2:].double()
    y = _jet(g.pos, 3.5 * h, h)(z)
    grad, lap, det = y[:, 1] / h, y[:, 2] / h ** 2, y[:, 3] / h ** 4
    zz = z[:, 0]
    assert (grad - torch.sqrt(1 - zz ** 2)).abs().max() < 2e-3
    assert (lap + 2 * zz).abs().max() < 2e-2
    assert (det - zz ** 2).abs().max() < 2e-2


def test_too_few_neighbours_is_a_clear_error():
    g = grids.icosahedral(3)
    with pytest.raises(ValueError, match="larger radius"):
        _jet(g.pos, 1.1 * g.spacing, g.spacing)
    with pytest.raises(ValueError, match="points"):
        _jet(g.pos, 3.5 * g.spacing, g.spacing)(torch.zeros(10, 1))
