"""LocalJet and GradientPairs: exact rotation invariance and analytic values."""

import pytest
import torch

from usf_graph import grids
from usf_graph.geometry import normalize, random_rotation, rotate
from usf_graph.nn import FillHidden, GradientPairs, LocalJet, UpJet, geodesic_radius_graph


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


def _pairs(pos, radius, h, channels, pairs):
    ei, ew = geodesic_radius_graph(pos, radius)
    return GradientPairs(pos, ei, ew, h, channels, pairs).double()


def test_gradient_pairs_are_exactly_rotation_invariant():
    pos = normalize(torch.randn(400, 3, dtype=torch.float64,
                                generator=torch.Generator().manual_seed(0)))
    x = torch.randn(2, 400, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    layer = _pairs(pos, 0.5, 0.1, 5, 3)
    y = layer(x)
    assert y.shape == (2, 400, 6)
    assert torch.allclose(layer(x[1]), y[1], atol=1e-14)  # [N, C] and [B, N, C] agree
    for seed in range(3):
        R = random_rotation(seed=seed).double()
        rotated = _pairs(rotate(pos, R), 0.5, 0.1, 5, 3)  # new graph, new tangent frames
        rotated.load_state_dict(layer.state_dict())
        assert (rotated(x) - y).abs().max() < 1e-10
    assert y.abs().max() > 1e-2


def test_gradient_pairs_match_the_analytic_products():
    # a = z, b = x: grad z = e_z - z p, grad x = e_x - x p, so the dot product is -x z
    # and the cross product along p is p . (e_z x e_x) = y
    g = grids.icosahedral(5)
    h = g.spacing
    pos = g.pos.double()
    layer = _pairs(pos, 3.5 * h, h, 2, 1)
    with torch.no_grad():
        layer.lin.weight.copy_(torch.eye(2, dtype=torch.float64))
    y = layer(torch.stack([pos[:, 2], pos[:, 0]], 1)) / h ** 2
    assert (y[:, 0] + pos[:, 0] * pos[:, 2]).abs().max() < 5e-3
    assert (y[:, 1] - pos[:, 1]).abs().max() < 5e-3


def test_gradient_pairs_reject_bad_arguments():
    g = grids.icosahedral(2)
    with pytest.raises(ValueError, match="pairs"):
        _pairs(g.pos, 3.5 * g.spacing, g.spacing, 4, 0)
    layer = _pairs(g.pos, 3.5 * g.spacing, g.spacing, 4, 2)
    for x in (torch.zeros(len(g.pos), 3), torch.zeros(2, len(g.pos), 3)):  # [N, C], [B, N, C]
        with pytest.raises(ValueError, match="^x has 3 channels, the layer expects 4$"):
            layer(x.double())
    assert repr(layer) == f"GradientPairs(4, pairs=2, num_nodes=162, spacing={g.spacing:.4g})"


def test_gradient_pairs_gradcheck():
    g = grids.icosahedral(1)
    layer = _pairs(g.pos, 3.5 * g.spacing, g.spacing, 3, 2)
    x = torch.randn(2, len(g.pos), 3, dtype=torch.float64, requires_grad=True)
    W = layer.lin.weight.detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda x, W: torch.func.functional_call(layer, {"lin.weight": W}, (x,)), (x, W))


def _up_jet(pos, radius, h, c, fields=None):
    ei, ew = geodesic_radius_graph(pos, radius)
    return UpJet(pos, ei, ew, h, c, fields).double()


def test_up_jet_is_exactly_invariant_when_up_turns_with_the_image():
    gen = torch.Generator().manual_seed(0)
    pos = normalize(torch.randn(400, 3, dtype=torch.float64, generator=gen))
    x = torch.randn(2, 400, 3, dtype=torch.float64, generator=gen)
    up = normalize(torch.randn(2, 3, dtype=torch.float64, generator=gen))
    torch.manual_seed(0)
    layer = _up_jet(pos, 0.5, 0.1, 3, fields=4)
    y = layer(x, up)
    assert y.shape == (2, 400, 20)
    for seed in range(3):
        R = random_rotation(seed=seed).double()
        turned = _up_jet(rotate(pos, R), 0.5, 0.1, 3, fields=4)  # new graph, new frames
        turned.load_state_dict(layer.state_dict())
        assert (turned(x, rotate(up, R)) - y).abs().max() < 1e-10
    # but it does read up: another up, other numbers
    assert (layer(x, up.flip(0)) - y).abs().max() > 1e-2


def test_up_jet_of_a_linear_function_matches_the_analytic_derivatives():
    # f = p . a: surface gradient a - (a.p) p, Hessian -(a.p) I on the tangent plane
    g = grids.icosahedral(5)
    h, p = g.spacing, g.pos.double()
    a = torch.tensor([0.3, -0.8, 0.5], dtype=torch.float64)
    u = normalize(torch.tensor([[0.2, -0.3, 0.9]], dtype=torch.float64))
    y = _up_jet(g.pos, 3.5 * h, h, 1)((p @ a)[None, :, None], u)[0]
    t = u - (p @ u[0])[:, None] * p  # up's tangential part, |t| = sin(angle to up)
    e = torch.linalg.cross(t, p)
    ap, t2 = p @ a, (t * t).sum(1)
    assert (y[:, 0] / h - t @ a).abs().max() < 2e-3
    assert (y[:, 1] / h - e @ a).abs().max() < 2e-3
    assert (y[:, 2] / h ** 2 + ap * t2).abs().max() < 2e-2
    assert (y[:, 3] / h ** 2).abs().max() < 2e-2
    assert (y[:, 4] / h ** 2 + ap * t2).abs().max() < 2e-2
    assert (e @ a).abs().max() > 0.5 and (t @ a).abs().max() > 0.5  # both directions bite


def test_up_jet_rejects_bad_shapes():
    g = grids.icosahedral(2)
    layer = _up_jet(g.pos, 3.5 * g.spacing, g.spacing, 3, fields=2)
    x = torch.zeros(2, len(g.pos), 3, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"up \[B, 3\]"):
        layer(x, torch.zeros(1, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="x"):
        layer(x[..., :2], torch.zeros(2, 3, dtype=torch.float64))
    assert repr(layer) == f"UpJet(3, fields=2, num_nodes=162, spacing={g.spacing:.4g})"


def test_jets_on_a_pyg_batch_equal_each_graph_alone():
    g = grids.icosahedral(2)
    ei, ew = geodesic_radius_graph(g.pos, 3.5 * g.spacing)
    x = torch.randn(2 * len(g), 2, dtype=torch.float64)
    batch = torch.arange(2).repeat_interleave(len(g))
    for layer in (LocalJet(g.pos, ei, ew, g.spacing),
                  GradientPairs(g.pos, ei, ew, g.spacing, 2, 3).double()):
        y = layer(x, batch=batch)
        for i in range(2):
            torch.testing.assert_close(y[batch == i], layer(x[batch == i]), rtol=0, atol=1e-14)
        torch.testing.assert_close(layer(x.view(2, len(g), 2)).reshape(y.shape), y)
        with pytest.raises(ValueError, match=f"grid of {len(g)}"):
            layer(x[:10])


def test_fill_hidden_takes_the_nearest_visible_values_and_averages_ties():
    pos = torch.tensor([[1.0, 0, 0], [0, 1, 0], [-1, 0, 0], [0, 0, 1], [0.6, 0.8, 0]])
    fill = FillHidden(pos)
    x = torch.tensor([[[1.0], [2.0], [3.0], [4.0], [5.0]]])
    mask = torch.tensor([True, False, True, False, False])
    # point 1 (0,1,0) is nearest to nothing visible but equally far from 0 and 2: the mean;
    # point 3 (0,0,1) too; point 4 is nearest to point 0
    torch.testing.assert_close(fill(x, mask)[0, :, 0], torch.tensor([1.0, 2.0, 3.0, 2.0, 1.0]))
    assert fill(x, None) is x
    everything = torch.ones(5, dtype=torch.bool)  # nothing hidden: unchanged
    torch.testing.assert_close(fill(x, everything), x)


def test_jets_share_a_fit_only_with_the_same_graph():
    """Layers on one graph reuse one least-squares fit (kept in memory by the graph's
    content); another graph of the same size, another sigma or a graph whose distances need
    gradients each get their own, equal to a fit made from scratch."""
    from usf_graph.nn import SurfaceJet, jet_operator
    from usf_graph.nn.jet import _FITS

    g = grids.icosahedral(2)
    h = float(g.spacing)
    ei, ew = geodesic_radius_graph(g.pos, 3.5 * h)
    a = SurfaceJet(g.pos, ei, ew, h)
    hits = _FITS.hits
    b = SurfaceJet(g.pos, ei, ew, h)
    assert a.op_val.data_ptr() == b.op_val.data_ptr() and _FITS.hits == hits + 1  # one storage
    # the same edges and distances on other points: a different operator, not the cached one
    pos2 = rotate(g.pos, random_rotation(seed=3, dtype=g.pos.dtype))
    c = SurfaceJet(pos2, ei, ew, h)
    fresh = jet_operator(pos2, ei, ew, float(ew.max()) / 2)
    assert torch.equal(c.op_val, fresh.values()) and not torch.allclose(c.op_val, a.op_val)
    d = SurfaceJet(g.pos, ei, ew, h, sigma=h)  # another width
    assert torch.equal(d.op_val, jet_operator(g.pos, ei, ew, h).values())
    two = jet_operator(g.pos, ei, ew, h, rows=2).to_dense()  # the gradient rows alone
    assert two.shape == (2 * len(g), len(g))
    full = jet_operator(g.pos, ei, ew, h).to_dense().reshape(len(g), 5, len(g))
    torch.testing.assert_close(two.reshape(len(g), 2, len(g)), full[:, :2], rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="rows must be 2 .* or 5"):
        jet_operator(g.pos, ei, ew, h, rows=3)
    assert not torch.allclose(d.op_val, a.op_val)
    # distances that need gradients: fitted afresh, and the gradient reaches them
    w = ew.double().clone().requires_grad_(True)
    e = SurfaceJet(g.pos.double(), ei, w, h)
    assert e.op_val.requires_grad and e.op_val.data_ptr() != a.op_val.data_ptr()
    e.op_val.sum().backward()
    assert w.grad is not None and torch.isfinite(w.grad).all() and w.grad.abs().sum() > 0


def test_jet_operator_is_the_weighted_least_squares_fit_it_documents():
    """Against a fit written here, at a few points of a random signal (no polynomial, so
    the weights matter): log-map coordinates, weights exp(-d^2 / 2 sigma^2), the six
    terms, numpy's least squares; compared through the gradient's length and the Hessian's
    trace and determinant, which no choice of tangent frame changes."""
    import numpy as np

    from usf_graph.nn.jet import jet_operator

    g = grids.icosahedral(3)
    ei, ew = geodesic_radius_graph(g.pos, 3.5 * g.spacing)
    sigma = 1.5 * g.spacing
    f = torch.randn(len(g), dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    out = (jet_operator(g.pos, ei, ew, sigma) @ f[:, None]).reshape(len(g), 5).numpy()
    p_all, fn = g.pos.numpy(), f.numpy()
    j, i = ei.numpy()
    for p in (0, 17, 300, 641):
        q = j[i == p]
        t = p_all[q] - (p_all[q] @ p_all[p])[:, None] * p_all[p]
        d = np.arccos(np.clip(p_all[q] @ p_all[p], -1, 1))
        norm = np.linalg.norm(t, axis=1)
        u = np.where(norm[:, None] > 0, t / np.where(norm > 0, norm, 1)[:, None], 0) * d[:, None]
        a = np.cross([0.3, -0.5, 0.8], p_all[p])  # any tangent frame
        a /= np.linalg.norm(a)
        b = np.cross(p_all[p], a)
        u1, u2 = u @ a, u @ b
        M = np.stack([np.ones_like(u1), u1, u2, u1 * u1 / 2, u1 * u2, u2 * u2 / 2], 1)
        sw = np.exp(-0.25 * (d / sigma) ** 2)  # the square root of the weights
        c = np.linalg.lstsq(M * sw[:, None], fn[q] * sw, rcond=None)[0]
        for got, want in ((np.hypot(*out[p, :2]), np.hypot(c[1], c[2])),
                          (out[p, 2] + out[p, 4], c[3] + c[5]),
                          (out[p, 2] * out[p, 4] - out[p, 3] ** 2, c[3] * c[5] - c[4] ** 2)):
            assert abs(got - want) < 1e-8 * (1 + abs(want)), (p, got, want)
