"""Half precision: the sums over a neighbourhood run in float32, and casting a module to
half precision leaves its geometry alone."""

import copy

import torch

from tests.helpers import random_sphere
from tests.nn.test_conv import dense_reference, graph
from usf_graph.nn import SphericalConv
from usf_graph.nn.precision import GeometryModule, accumulate_in


def test_accumulate_in():
    assert accumulate_in(torch.bfloat16) == accumulate_in(torch.float16) == torch.float32
    assert accumulate_in(torch.float32) == torch.float32
    assert accumulate_in(torch.float64) == torch.float64


def test_half_casts_keep_geometry_and_cast_everything_else():
    m = GeometryModule()
    m.weight = torch.nn.Parameter(torch.ones(3, dtype=torch.float64))
    m.register_buffer("pos", torch.linspace(0, 1, 5, dtype=torch.float64), persistent=False)
    m.register_buffer("area", torch.linspace(0, 1, 5, dtype=torch.float32), persistent=False)
    m.register_buffer("running_mean", torch.zeros(3, dtype=torch.float32))  # persistent: cast
    m.register_buffer("index", torch.arange(5), persistent=False)
    pos = m.pos
    for cast in (lambda: m.bfloat16(), lambda: m.half(), lambda: m.to(torch.float16)):
        cast()
        assert m.weight.dtype in (torch.bfloat16, torch.float16)
        assert m.running_mean.dtype == m.weight.dtype
        assert m.pos is pos and m.area.dtype == torch.float32 and m.index.dtype == torch.long
    m.double()  # every other cast applies to geometry as to any buffer
    assert m.pos.dtype == m.area.dtype == m.running_mean.dtype == torch.float64
    m.float()
    assert m.pos.dtype == torch.float32
    # the casts reach the module's children, geometry or not
    m.child, m.geo = torch.nn.Linear(2, 2), GeometryModule()
    m.geo.register_buffer("pos", torch.zeros(4, dtype=torch.float32), persistent=False)
    m.half()
    assert m.child.weight.dtype == torch.float16 and m.geo.pos.dtype == torch.float32
    m.double()
    assert m.child.weight.dtype == m.geo.pos.dtype == torch.float64


def test_half_precision_layer_follows_its_float64_reference():
    """A bfloat16 or float16 layer and input: float32 coefficients (cached as such) over
    float64 geometry, the output in the input's dtype within its rounding (about 9% off for
    bfloat16 when the distances and areas were rounded too); gradients reach the input and
    the weight."""
    pos = random_sphere(150, 6, dtype=torch.float64)
    ei, ew, area = graph(pos, 0.5)
    conv = SphericalConv(3, 4, 0.5, num_basis=3, basis="gaussian").double()
    conv.bind(ei, ew, node_weight=area)
    x = torch.randn(2, 150, 3, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    fov = torch.rand(150, generator=torch.Generator().manual_seed(7)) > 0.3
    ref = dense_reference(x, pos, conv, area, fov).detach()
    for dtype, tol in ((torch.bfloat16, 5e-3), (torch.float16, 1e-3)):
        low = copy.deepcopy(conv).to(dtype)
        assert low.weight.dtype == dtype and low.bound_edge_weight.dtype == torch.float64
        y = low(x.to(dtype), mask=fov).detach()
        assert y.dtype == dtype and low._call_coef.dtype == torch.float32
        assert float((y.double() - ref).norm() / ref.norm()) < tol
        xb = x.to(dtype).requires_grad_()
        low(xb, mask=fov).float().square().sum().backward()
        assert xb.grad.dtype == dtype and torch.isfinite(xb.grad).all()
        assert low.weight.grad.dtype == dtype and low.weight.grad.abs().sum() > 0
