"""Radius and k-NN graphs on S2 and in R3: never truncated, exact distances."""

import math

import numpy as np
import pytest
import torch

from usf_graph import grids
from usf_graph.graph import euclidean_radius, geodesic_radius, nearest_with_ties
from usf_graph.nn import (
    geodesic_radius_graph,
    radius_for_neighbors,
)


def test_radius_graph_is_not_truncated():
    g = grids.fibonacci(3000)
    ei, ew = geodesic_radius_graph(g.pos, 0.35)  # ~90 neighbours: above the first cap of 64
    deg = torch.bincount(ei[1])
    from scipy.spatial import cKDTree
    ref = [len(n) for n in cKDTree(g.pos.numpy()).query_ball_point(g.pos.numpy(), 2 * math.sin(0.35 / 2))]
    assert deg.tolist() == ref and int(deg.max()) > 64
    assert (ew <= 0.35).all() and (ei[1][1:] >= ei[1][:-1]).all()
    np.testing.assert_allclose(ew.numpy(), torch.atan2(
        torch.linalg.cross(g.pos[ei[0]], g.pos[ei[1]]).norm(dim=1),
        (g.pos[ei[0]] * g.pos[ei[1]]).sum(1)).numpy(), rtol=1e-12, atol=1e-15)
    assert (ew[ei[0] == ei[1]] == 0).all()


def _assert_csr_order(ei):
    key = ei[1] * (int(ei[0].max()) + 1) + ei[0]
    assert (key[1:] > key[:-1]).all()  # by centre, then neighbour, no repeats


def test_every_graph_is_sorted_by_centre_then_neighbour_and_refuses_nan():
    from usf_graph.nn import euclidean_radius, euclidean_radius_graph, geodesic_radius, knn_graph

    gen = torch.Generator().manual_seed(1)
    pos = grids.fibonacci(500).pos
    centres = torch.nn.functional.normalize(torch.randn(40, 3, generator=gen, dtype=pos.dtype), dim=1)
    for ei in (geodesic_radius_graph(pos, 0.3)[0], geodesic_radius(pos, centres, 0.3)[0],
               euclidean_radius_graph(pos, 0.3)[0], euclidean_radius(pos, centres, 0.3)[0],
               knn_graph(pos, 9)[0]):
        _assert_csr_order(ei)
    bad = pos.clone()
    bad[7, 1] = float("inf")
    for build in (lambda: geodesic_radius_graph(bad, 0.3), lambda: euclidean_radius(bad, centres, 0.3),
                  lambda: knn_graph(bad, 3)):
        with pytest.raises(ValueError, match="NaN or inf; cannot build a graph"):
            build()
    for bad in (0.0, -0.1, float("nan")):
        with pytest.raises(ValueError, match="radius must be > 0"):
            euclidean_radius_graph(pos, bad)
        with pytest.raises(ValueError, match="radius must be > 0"):
            euclidean_radius(pos, centres, bad)
    with pytest.raises(ValueError, match="points are torch.float64 but centres are torch.float32"):
        geodesic_radius(pos, centres.float(), 0.3)


@pytest.mark.parametrize("kind", ["geodesic", "euclidean"])
def test_bipartite_graphs_match_brute_force(kind):
    """Edges from points to centres: exactly the pairs within the radius (a boundary pair
    included), with their distances; radius pi on the sphere takes every pair."""
    from usf_graph.nn import euclidean_radius, geodesic_radius

    gen = torch.Generator().manual_seed(2)
    pos = torch.nn.functional.normalize(torch.randn(200, 3, generator=gen, dtype=torch.float64), dim=1)
    centres = torch.nn.functional.normalize(torch.randn(30, 3, generator=gen, dtype=torch.float64), dim=1)
    if kind == "geodesic":
        dist = torch.atan2(torch.linalg.cross(pos[:, None], centres[None].expand(200, 30, 3)).norm(dim=-1),
                           pos @ centres.T)
        build = geodesic_radius
    else:
        dist = torch.cdist(pos, centres)
        build = euclidean_radius
    r = float(dist[5, 3])  # point 5 lies on centre 3's boundary
    ei, w = build(pos, centres, r)
    want = (dist <= r).nonzero()
    assert sorted(map(tuple, ei.T.tolist())) == sorted(map(tuple, want.tolist()))
    torch.testing.assert_close(w, dist[ei[0], ei[1]], rtol=1e-12, atol=1e-15)
    if kind == "geodesic":
        assert build(pos, centres, math.pi)[0].shape[1] == 200 * 30
        for bad in (0.0, math.pi + 1e-9, float("nan")):
            with pytest.raises(ValueError, match=r"radius must be in \(0, pi\]"):
                build(pos, centres, bad)


def test_euclidean_graphs_match_brute_force():
    from scipy.spatial import cKDTree

    from usf_graph.nn import euclidean_radius_graph, knn_graph

    gen = torch.Generator().manual_seed(0)
    pos = torch.cat([torch.randn(300, 3, generator=gen, dtype=torch.float64),
                     0.01 * torch.randn(100, 3, generator=gen, dtype=torch.float64)])  # a dense clump
    ei, ew = euclidean_radius_graph(pos, 0.3)
    tree = cKDTree(pos.numpy())
    ref = tree.query_ball_point(pos.numpy(), 0.3)
    assert torch.bincount(ei[1], minlength=len(pos)).tolist() == [len(n) for n in ref]
    assert max(len(n) for n in ref) > 100  # past the first neighbour cap: nothing truncated
    for i in (0, 350):
        assert sorted(ei[0][ei[1] == i].tolist()) == sorted(ref[i])
    torch.testing.assert_close(ew, (pos[ei[0]] - pos[ei[1]]).norm(dim=1), rtol=0, atol=0)
    ei, ew = knn_graph(pos[:300], 8)
    d, nb = cKDTree(pos[:300].numpy()).query(pos[:300].numpy(), k=8)
    assert (torch.bincount(ei[1]) == 8).all()
    for i in (0, 17, 299):
        assert sorted(ei[0][ei[1] == i].tolist()) == sorted(nb[i].tolist())
    np.testing.assert_allclose(np.sort(ew.reshape(300, 8).numpy(), 1), d, rtol=1e-12)
    assert knn_graph(pos, 1)[0].tolist() == [list(range(400))] * 2  # each point its own nearest
    for bad in (0, 2.5):
        with pytest.raises(ValueError, match="positive integer"):
            knn_graph(pos, bad)
    with pytest.raises(ValueError, match="NaN"):
        knn_graph(torch.full((5, 3), float("nan")), 2)


@pytest.mark.parametrize("grid", ["fibonacci:4000", "icosahedral:4", "healpix:16"])
def test_radius_for_neighbors_holds_about_k_points(grid):
    """A cap of the radius holds k grid points (self included) on average, give or take the
    shell a lattice's small caps take whole (7.8 on a Fibonacci grid for k = 7, 32.5 on the
    icosahedral one for k = 30); bad k is refused."""
    g = grids.from_spec(grid)
    n = len(g)
    for k in (7, 30, 120):
        r = radius_for_neighbors(n, k)
        assert 2 * math.pi * (1 - math.cos(r)) == pytest.approx(4 * math.pi * k / n, rel=1e-12)
        ei, _ = geodesic_radius_graph(g.pos, r)
        assert len(ei[1]) / n == pytest.approx(k, abs=1 + 0.1 * k)
    assert radius_for_neighbors(n, 0.5) > 0  # half a point on average: a valid, tiny cap
    for bad in (0, -1, n):
        with pytest.raises(ValueError, match=rf"k must be in \(0, {n}\)"):
            radius_for_neighbors(n, bad)


@pytest.mark.parametrize("n", [1, 3])
def test_nearest_with_ties_keeps_every_point_tied_with_the_nth(n):
    """Against brute force: the n nearest and every point as near as the n-th, on the
    icosahedral grids (where the midpoints' ties are exact) and on random points."""
    rng = np.random.default_rng(0)
    cases = [(grids.icosahedral(1).pos.numpy(), grids.icosahedral(2).pos.numpy()),
             (grids.icosahedral(3).pos.numpy(), grids.icosahedral(4).pos.numpy()),
             (rng.normal(size=(50, 3)), rng.normal(size=(40, 3)))]
    for points, queries in cases:
        d, j = nearest_with_ties(points, queries, n)
        full = np.linalg.norm(queries[:, None] - points[None], axis=-1)
        nth = np.sort(full, 1)[:, n - 1:n]
        want = full <= nth * (1 + 1e-9)
        assert want.sum(1).max() > n or points.shape[0] == 50  # the grids do tie
        for q in range(len(queries)):
            got = j[q][np.isfinite(d[q])]
            assert sorted(got.tolist()) == np.flatnonzero(want[q]).tolist()
            np.testing.assert_allclose(d[q][np.isfinite(d[q])], full[q, got], rtol=1e-12)


def test_face_centres_keep_all_three_tied_vertices():
    """An icosahedron's face centre is as near to three vertices: more ties than the first
    search (2 n candidates) holds, so the search must widen rather than stop."""
    from itertools import combinations

    pts = grids.icosahedral(0).pos.double().numpy()
    dist = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    edge = dist[dist > 0].min()
    faces = [f for f in combinations(range(12), 3)
             if all(np.isclose(dist[a, b], edge) for a, b in combinations(f, 2))]
    assert len(faces) == 20
    centres = np.stack([pts[list(f)].sum(0) for f in faces])
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    d, j = nearest_with_ties(pts, centres, 1)
    for q, f in enumerate(faces):
        assert sorted(j[q][np.isfinite(d[q])].tolist()) == list(f)


def test_radius_searches_keep_self_loops_by_default():
    """Called on one point set, both searches include each point itself (distance 0)."""
    pos = grids.icosahedral(1).pos.double()
    for ei, w in (geodesic_radius(pos, None, 0.3), euclidean_radius(pos, pos, 0.3)):
        loops = ei[0] == ei[1]
        assert int(loops.sum()) == len(pos) and float(w[loops].abs().max()) < 1e-12
