"""Equivariance on real grids: the network adds little beyond interpolation error, while
Conv2d on the equirectangular image does not come close."""

import pytest
import torch

from usf_graph import grids
from usf_graph.geometry import random_rotation
from usf_graph.testing import (
    equirect_equivariance_error,
    grid_equivariance_error,
    random_spherical_net,
    smooth_signal,
)


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
