"""The equivariance harness passes what is equivariant and catches what is not; on real
grids the network adds little beyond interpolation error, while Conv2d on the
equirectangular image does not come close."""

import math
from itertools import count

import pytest
import torch

from usf_graph import grids
from usf_graph.geometry import random_rotation, rotation_from_axis_angle
from usf_graph.testing import (
    _rel,
    assert_equivariant,
    assert_motion_invariant,
    equirect_equivariance_error,
    grid_equivariance_error,
    random_spherical_net,
    smooth_signal,
)

POS = grids.icosahedral(1).pos.double()
R5 = rotation_from_axis_angle(POS[0], 2 * math.pi / 5)  # a symmetry of the grid
KERNEL = torch.exp(-torch.cdist(POS, POS, compute_mode="donot_use_mm_for_euclid_dist") ** 2)  # equivariant


def _blur(x):
    return KERNEL.to(x.dtype) @ x


def test_the_harness_passes_equivariant_layers_and_catches_the_rest():
    x = torch.randn(2, len(POS), 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    assert assert_equivariant(_blur, x, POS, R5) < 1e-13
    z = POS[:, 2:3]  # a fixed north breaks it
    with pytest.raises(AssertionError, match="not equivariant: max error"):
        assert_equivariant(lambda t: _blur(t) + z, x, POS, R5)
    assert assert_equivariant(lambda t: _blur(t) + z, x, POS, R5, atol=10.0) > 0.1
    # invariant outputs: a sum over points is one, the first point's value is not
    assert assert_equivariant(lambda t: t.sum(-2), x, POS, R5, invariant=True) < 1e-14
    with pytest.raises(AssertionError, match="not equivariant"):
        assert_equivariant(lambda t: t[..., 1, :], x, POS, R5, invariant=True)
    # out_dims: None marks one output invariant; in_dims: None leaves an input alone
    assert assert_equivariant(lambda t, s: (_blur(t) * s, t.sum(-2)), (x, torch.tensor(2.0)), POS, R5,
                              in_dims=(-2, None), out_dims=(-2, None)) < 1e-13
    # a mask (1-D) is turned along its only axis and must come out turned
    mask = POS[:, 0] > 0.2
    assert assert_equivariant(lambda t, m: (t * m[:, None], m), (x, mask), POS, R5) == 0.0
    for labels in (mask, mask.long()):  # a mask, or integer labels
        with pytest.raises(AssertionError, match="a discrete output .* does not follow the rotation"):
            assert_equivariant(lambda t, m, k=labels: (t, k.roll(1)), (x, mask), POS, R5)
    # an output on another point set (a pool onto the 12 vertices)
    vertices = grids.icosahedral(0).pos.double()
    keep = torch.cdist(vertices, POS).argmin(1)
    assert assert_equivariant(lambda t: t[..., keep, :], x, POS, R5, out_pos=vertices) == 0.0
    with pytest.raises(ValueError, match="R does not map the points onto themselves"):
        assert_equivariant(_blur, x, POS, rotation_from_axis_angle(POS[0], math.pi / 5))
    calls = count()
    with pytest.raises(AssertionError, match=r"output shapes differ: \(2, 42, 2\) vs \(2, 42, 3\)"):
        assert_equivariant(lambda t: t[..., : 3 - next(calls)], x, POS, R5)


def test_the_default_tolerance_follows_the_dtype():
    """1e-10 relative in float64, 1e-5 in float32, 1e-3 otherwise (float16)."""
    half = torch.full((len(POS), 1), 0.5)
    # one float16 step (2^-11) more in the northern points: a relative error of 9.8e-4
    nudged = lambda t: t + 2.0 ** -11 * (POS[:, 2:3] > 0).to(t.dtype)  # noqa: E731
    for dtype in (torch.float64, torch.float32):
        with pytest.raises(AssertionError, match="not equivariant"):
            assert_equivariant(nudged, half.to(dtype), POS, R5)
    assert 9e-4 < assert_equivariant(nudged, half.half(), POS, R5) < 1e-3
    assert assert_equivariant(nudged, half.double(), POS, R5, atol=1e-3) < 1e-3


def test_the_motion_harness_passes_distances_and_catches_coordinates():
    pts = torch.randn(30, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    spread = lambda p: torch.cdist(p, p, compute_mode="donot_use_mm_for_euclid_dist").sum(-1, keepdim=True)  # noqa: E731
    assert assert_motion_invariant(spread, pts, translation=[1.0, -2.0, 0.5]) < 1e-13
    with pytest.raises(AssertionError, match="not equivariant"):  # the default rotation moves them
        assert_motion_invariant(lambda p: p[:, :1], pts)
    norm = lambda p: p.norm(dim=-1)  # noqa: E731 (rotation-invariant, not translation-invariant)
    assert assert_motion_invariant(norm, pts, rotation=R5) < 1e-14
    with pytest.raises(AssertionError, match="not equivariant"):
        assert_motion_invariant(norm, pts, rotation=R5, translation=[0.0, 0.0, 1.0])


def test_the_relative_error_is_area_weighted():
    a, b = torch.tensor([[1.0, 2.0], [3.0, 4.0]], dtype=torch.float64), torch.tensor([[1.0, 1.0], [2.0, 2.0]], dtype=torch.float64)
    w = torch.tensor([1.0, 3.0], dtype=torch.float64)
    want = math.sqrt((1 * (0 + 1) + 3 * (1 + 4)) / (1 * 2 + 3 * 8))
    assert _rel(a, b, w) == pytest.approx(want, rel=1e-12)


@pytest.mark.parametrize("spec", ["icosahedral:4", "healpix:16", "fibonacci:2562"])
def test_network_adds_little_beyond_interpolation(spec):
    g = grids.from_spec(spec)
    e = grid_equivariance_error(random_spherical_net(g), g, smooth_signal, random_rotation(seed=7))
    assert e["interpolation"] < 3e-3
    assert e["ratio"] < 2.5, e


def test_kernel_finer_than_the_grid_breaks_equivariance():
    # hat functions 0.67 grid spacings apart resolve single neighbours, so the kernel the
    # grid realizes differs from node to node (see the README on choosing radius and K)
    g = grids.icosahedral(4)
    e = grid_equivariance_error(random_spherical_net(g, 2.0, 4, "hat"), g, smooth_signal, random_rotation(seed=7))
    assert e["ratio"] > 20, e


def test_conv2d_on_equirectangular_is_far_from_equivariant():
    torch.manual_seed(0)
    conv = torch.nn.Sequential(torch.nn.Conv2d(3, 16, 3, padding=1), torch.nn.Tanh(),
                               torch.nn.Conv2d(16, 8, 3, padding=1)).double()
    e = equirect_equivariance_error(conv, smooth_signal, random_rotation(seed=7), width=128)
    assert e["interpolation"] < 3e-3
    assert e["ratio"] > 50 and e["network"] > 0.05, e
