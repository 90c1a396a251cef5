"""DistanceKernel: support, values at 0 and at the radius."""


import pytest
import torch

from usf_graph.nn import (
    DistanceKernel,
)


@pytest.mark.parametrize("basis", ["hat", "gaussian", "bessel", "mlp"])
def test_kernel_vanishes_at_radius_and_is_finite_at_zero(basis):
    k = DistanceKernel(5, 0.3, basis)
    d = torch.tensor([0.0, 0.1, 0.2999999, 0.3, 0.5])
    v = k(d)
    assert v.shape == (5, 5) and torch.isfinite(v).all()
    assert v[3:].abs().max() == 0 and v[2].abs().max() < 1e-4
    if basis == "hat":
        torch.testing.assert_close(v[:2].sum(1), torch.ones(2))
