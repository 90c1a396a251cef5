"""Every public layer of usf_graph.nn through the equivariance harness, in float64 (1e-10)
and float32 (usf_graph.testing.TOLERANCE: 1e-5 relative to the output's scale)."""

import math

import pytest
import torch

from tests.helpers import random_sphere
from usf_graph import grids
from usf_graph.geometry import rotation_from_axis_angle
from usf_graph.nn import (
    FPSPool,
    GaussianPool,
    GradientPairs,
    GridPool,
    GridUnpool,
    LocalJet,
    MaskedBatchNorm,
    PointConv,
    SphericalConv,
    euclidean_radius_graph,
    geodesic_radius_graph,
    global_max_pool_masked,
    global_mean_pool_area,
)
from usf_graph.testing import TOLERANCE, assert_equivariant, assert_motion_invariant

FINE = grids.healpix(8)
COARSE, CLUSTER = FINE.coarsen()
R = rotation_from_axis_angle(torch.tensor([0.0, 0, 1], dtype=torch.float64),
                              torch.tensor(math.pi / 2, dtype=torch.float64))


def layers():
    """(name, module, call(module, x, mask), out_pos, out_dims) for every grid layer."""
    r = 1.7 * FINE.spacing
    ei, ew = geodesic_radius_graph(FINE.pos, r)
    ej, wj = geodesic_radius_graph(FINE.pos, 3.5 * FINE.spacing)
    bn = MaskedBatchNorm(3)
    return [
        ("SphericalConv", SphericalConv(3, 4, r, basis="gaussian").bind(ei, ew, FINE.area),
         lambda m, x, k: m(x, mask=k), None, -2),
        ("GridPool max", GridPool(CLUSTER, len(COARSE), "max"),
         lambda m, x, k: m(x, k), COARSE.pos, (-2, -1)),
        ("GridPool mean", GridPool(CLUSTER, len(COARSE), "mean", area=FINE.area),
         lambda m, x, k: m(x, k), COARSE.pos, (-2, -1)),
        ("GaussianPool", GaussianPool(FINE.pos, COARSE.pos, 0.5 * COARSE.spacing, FINE.area),
         lambda m, x, k: m(x, k), COARSE.pos, (-2, -1)),
        ("GridUnpool nearest", GridUnpool(CLUSTER), lambda m, x, k: m(_coarse(x)), None, -2),
        ("GridUnpool linear", GridUnpool(CLUSTER, "linear", FINE.pos, COARSE.pos),
         lambda m, x, k: m(_coarse(x)), None, -2),
        ("MaskedBatchNorm", bn, lambda m, x, k: m(x, k, FINE.area), None, -2),
        ("LocalJet", LocalJet(FINE.pos, ej, wj, FINE.spacing), lambda m, x, k: m(x), None, -2),
        ("GradientPairs", GradientPairs(FINE.pos, ej, wj, FINE.spacing, 3, 4),
         lambda m, x, k: m(x), None, -2),
        ("global_mean_pool_area", None,
         lambda m, x, k: global_mean_pool_area(x, FINE.area, k), None, "invariant"),
        ("global_max_pool_masked", None, lambda m, x, k: global_max_pool_masked(x, k), None,
         "invariant"),
    ]


def _coarse(x):
    """GridUnpool's input: the first N(coarse) channels-last rows of a fine signal, which a
    symmetry permutes like the coarse grid (the grid is nested)."""
    return x[..., :len(COARSE), :]


@pytest.mark.parametrize("name", [entry[0] for entry in layers()])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_every_grid_layer_is_equivariant(name, dtype):
    _, module, call, out_pos, out_dims = next(e for e in layers() if e[0] == name)
    x = torch.randn(2, len(FINE), 3, generator=torch.Generator().manual_seed(0)).to(dtype)
    mask = FINE.pos[:, 0] > -0.4
    if module is not None:
        module = module.to(dtype)
    pos = FINE.pos
    if name.startswith("GridUnpool"):  # input on the coarse grid, output on the fine one
        x = x[..., :len(COARSE), :]
        def fn(x, m):  # noqa: E306
            return call(module, torch.cat([x, x.new_zeros(2, len(FINE) - len(COARSE), 3)], 1), m)
        err = assert_equivariant(fn, (x, mask[:len(COARSE)]), COARSE.pos, R, out_pos=FINE.pos)
    else:
        inv = out_dims == "invariant"
        err = assert_equivariant(lambda x, m: call(module, x, m), (x, mask), pos, R,
                                 out_pos=out_pos, out_dims=None if inv else out_dims,
                                 invariant=inv)
    assert err <= TOLERANCE[dtype]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_point_layers_are_invariant_to_rigid_motions(dtype):
    pos = (torch.randn(300, 3, generator=torch.Generator().manual_seed(0)) * 2).to(dtype)
    x = torch.randn(300, 4, generator=torch.Generator().manual_seed(1)).to(dtype)
    conv = PointConv(4, 5, 1.2).to(dtype)
    pool = FPSPool(ratio=0.25, radius=1.0)

    def net(p, x):
        ei, ew = euclidean_radius_graph(p, 1.2)
        h, _, _, idx = pool(torch.relu(conv(x, ei, ew)), p)
        return h, idx

    t = torch.tensor([1.0, -2.0, 0.5], dtype=dtype)
    assert assert_motion_invariant(net, pos, (x,), translation=t) <= TOLERANCE[dtype]


def test_spherical_conv_on_random_points_under_any_rotation():
    pos = random_sphere(300, 3)
    x = torch.randn(300, 2, generator=torch.Generator().manual_seed(2))
    conv = SphericalConv(2, 3, 0.4, normalize="mean")

    def run(p, x):
        ei, ew = geodesic_radius_graph(p, 0.4)
        return conv(x, ei, ew)

    assert assert_motion_invariant(run, pos, (x,)) < 1e-10
