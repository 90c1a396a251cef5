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


def _reference(basis: str, d, r: float, K: int):
    """The docstring's formulas, in numpy, one basis function at a time."""
    import numpy as np

    x = np.clip(d / r, 0, 1)
    env = 1 - 10 * x ** 3 + 15 * x ** 4 - 6 * x ** 5
    out = []
    for k in range(K):
        if basis == "hat":  # centre k r / K, width r / K
            v = np.maximum(0, 1 - np.abs(d - k * r / K) / (r / K))
        elif basis == "gaussian":  # centres evenly in [0, r], sigma r / K
            c = k * r / max(K - 1, 1)
            v = np.exp(-((d - c) ** 2) / (2 * (r / K) ** 2)) * env
        else:  # sqrt(2/r) sin(n pi d / r) / d, its limit n pi / r at 0
            n = k + 1
            with np.errstate(invalid="ignore", divide="ignore"):
                v = np.where(d > 0, np.sin(n * np.pi * d / r) / d, n * np.pi / r)
            v = np.sqrt(2 / r) * v * env
        out.append(np.where(d < r, v, 0.0))
    return np.stack(out, 1)


@pytest.mark.parametrize("basis", ["hat", "gaussian", "bessel"])
@pytest.mark.parametrize("K", [1, 2, 5])
def test_bases_are_their_formulas(basis, K):
    import numpy as np

    r = 0.37
    d = np.concatenate([[0.0, r], np.random.default_rng(K).uniform(0, 1.2 * r, 200)])
    got = DistanceKernel(K, r, basis)(torch.as_tensor(d)).numpy()
    np.testing.assert_allclose(got, _reference(basis, d, r, K), rtol=1e-12, atol=1e-12)
    if basis == "hat":  # a partition of unity up to the last centre
        inner = d <= (K - 1) * r / K
        np.testing.assert_allclose(got[inner].sum(1), 1.0, rtol=1e-12)


def test_bad_arguments_are_refused_and_repr_says_the_basis():
    for args, said in (((0, 0.3), "num_basis >= 1"), ((3, 0.0), "cutoff > 0"),
                       ((3, float("nan")), "cutoff > 0"), ((3, 0.3, "cosine"), "unknown basis 'cosine'")):
        with pytest.raises(ValueError, match=said):
            DistanceKernel(*args)
    assert repr(DistanceKernel(4, 0.25, "bessel")) == "DistanceKernel(num_basis=4, cutoff=0.25, basis='bessel')"
    k = DistanceKernel(3, 0.3, "mlp")
    assert k.learnable and not k.positive and DistanceKernel(3, 0.3).positive
    assert [m.out_features for m in k.mlp if hasattr(m, "out_features")] == [16, 3]  # hidden 16
    before = [p.clone() for p in k.parameters()]
    torch.manual_seed(1)
    k.reset_parameters()
    assert all((a != b).any() for a, b in zip(before, k.parameters()))
