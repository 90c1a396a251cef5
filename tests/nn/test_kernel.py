"""DistanceKernel: support, values at 0 and at the radius."""


import pytest
import torch

from usf_graph.nn import (
    DistanceKernel,
)
from usf_graph.nn.kernel import (
    envelope,
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


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_positive_bases_are_never_negative_near_the_radius(dtype):
    """The envelope's polynomial rounds below 0 just inside the radius (-8e-7 in float32);
    a normalization by those values once blew a hidden point's coefficients up to 1e3."""
    d = torch.linspace(0.29, 0.3, 200_001, dtype=dtype)
    for basis in ("hat", "gaussian"):
        assert DistanceKernel(3, 0.3, basis)(d).min() >= 0
    x = torch.linspace(0.0, 1.0, 200_001, dtype=dtype)
    assert envelope(x).min() >= 0 and envelope(x)[-1] == 0
