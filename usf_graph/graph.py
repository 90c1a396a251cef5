"""Radius and k-NN graphs on S2 (geodesic) and in R3 (euclidean), never truncated."""

from __future__ import annotations

import math

import numpy as np
import torch

from .geometry import geodesic_distance, geodesic_to_chord


def radius_for_neighbors(num_points: int, k: float) -> float:
    """Geodesic radius whose cap holds about ``k`` points (self included) of a uniform
    grid of ``num_points``: the cap area 2 pi (1 - cos r) = 4 pi k / N."""
    if not 0 < k < num_points:
        raise ValueError(f"k must be in (0, {num_points}), got {k}")
    return 2 * math.asin(math.sqrt(k / num_points))


def _radius_edges(pos: torch.Tensor, r: float, batch, loop: bool, centres=None,
                  batch_centres=None) -> torch.Tensor:
    """torch_cluster radius search with a neighbour cap that provably truncated nothing.

    Without ``centres``: the graph on ``pos``. With ``centres``: bipartite edges from
    ``pos`` (row 0) to ``centres`` (row 1). Sorted by centre, then neighbour.
    """
    import torch_cluster

    _check_finite(pos)
    if centres is not None and centres.dtype != pos.dtype:
        raise ValueError(f"points are {pos.dtype} but centres are {centres.dtype}: give both "
                         "in one dtype (e.g. centres.to(pos.dtype))")
    num_centres = pos.shape[0] if centres is None else centres.shape[0]
    cap = 64
    while True:
        if centres is None:
            ei = torch_cluster.radius_graph(pos, r, batch=batch, loop=loop, max_num_neighbors=cap)
        else:
            ei = torch_cluster.radius(pos, centres, r, batch, batch_centres,
                                      max_num_neighbors=cap).flip(0)
        deg = torch.bincount(ei[1], minlength=num_centres)
        # the search asks for cap (+1 without self-loops) candidates per node; a node
        # that reached it may have lost neighbours, so retry with a larger cap.
        if deg.numel() == 0 or int(deg.max()) < cap:
            break
        cap *= 4
    return _by_centre(ei, pos.shape[0])


def _check_finite(pos: torch.Tensor) -> None:
    if not torch.isfinite(pos).all():
        raise ValueError("positions contain NaN or inf; cannot build a graph")


def _by_centre(ei: torch.Tensor, num_sources: int) -> torch.Tensor:
    """Edges sorted by centre (row 1), then neighbour (row 0): CSR order."""
    return ei[:, torch.argsort(ei[1] * num_sources + ei[0])]


def geodesic_radius_graph(pos: torch.Tensor, radius: float, batch=None, loop: bool = True):
    """Edges between unit vectors within geodesic ``radius`` (radians).

    Searches on the chord 2 sin(r/2). Returns ``edge_index [2, E]`` (row 0: neighbour j,
    row 1: centre i, sorted by i) and ``edge_weight [E]``: the geodesic distance
    atan2(|p x q|, p . q) in ``pos``'s dtype. Self-loops (d = 0) are included by default.
    """
    ei, w = geodesic_radius(pos, None, radius, batch, loop=loop)
    w = torch.where(ei[0] == ei[1], torch.zeros_like(w), w)  # exact 0 on self-loops
    return ei, w


def check_radius(radius: float) -> float:
    """``radius`` as a float, refused unless it is a geodesic radius in (0, pi]."""
    if not 0 < radius <= math.pi:
        raise ValueError(f"radius must be in (0, pi] radians, got {radius}")
    return float(radius)


def geodesic_radius(pos: torch.Tensor, centres: torch.Tensor | None, radius: float, batch=None,
                    loop: bool = True):
    """Edges from unit vectors ``pos`` (row 0) to ``centres`` (row 1; ``None``: ``pos``
    itself) within geodesic ``radius``, searched on the chord 2 sin(r/2), never truncated;
    ``edge_weight`` = atan2 geodesic distance."""
    check_radius(radius)
    chord = float(geodesic_to_chord(radius)) * (1 + 1e-12)
    if centres is None:
        ei = _radius_edges(pos.detach(), chord, batch, loop)
        w = geodesic_distance(pos[ei[0]], pos[ei[1]])
    else:
        ei = _radius_edges(pos.detach(), chord, batch, True, centres.detach())
        w = geodesic_distance(pos[ei[0]], centres[ei[1]])
    keep = w <= radius
    return ei[:, keep], w[keep]


def euclidean_radius_graph(pos: torch.Tensor, radius: float, batch=None, loop: bool = True):
    """Edges within euclidean ``radius`` in R3 (``|p_j - p_i| <= radius``), with
    ``edge_weight`` = |p_j - p_i|."""
    return euclidean_radius(pos, pos, radius, batch, batch, loop)


def euclidean_radius(pos: torch.Tensor, centres: torch.Tensor, radius: float, batch=None,
                     batch_centres=None, loop: bool = True):
    """Bipartite edges from points ``pos`` (row 0) to ``centres`` (row 1) within euclidean
    ``radius`` (the boundary included, as on the sphere), never truncated; ``edge_weight`` =
    distance. ``centres is pos`` gives the graph on ``pos`` (``loop``: with self-loops)."""
    if not radius > 0:
        raise ValueError(f"radius must be > 0, got {radius}")
    # torch_cluster keeps d < r; search a hair wider, then keep d <= r exactly
    wider = float(radius) * (1 + 1e-12)
    if centres is pos:
        ei = _radius_edges(pos.detach(), wider, batch, loop)
    else:
        ei = _radius_edges(pos.detach(), wider, batch, True, centres.detach(), batch_centres)
    w = (pos[ei[0]] - centres[ei[1]]).norm(dim=-1)
    keep = w <= radius
    return ei[:, keep], w[keep]


def knn_graph(pos: torch.Tensor, k: int, batch=None, loop: bool = True):
    """k nearest neighbours (self included when ``loop``), euclidean ``edge_weight``."""
    import torch_cluster

    if int(k) != k or k < 1:
        raise ValueError(f"k must be a positive integer, got {k!r}")
    _check_finite(pos)
    ei = _by_centre(torch_cluster.knn_graph(pos.detach(), int(k), batch=batch, loop=loop),
                    pos.shape[0])
    return ei, (pos[ei[0]] - pos[ei[1]]).norm(dim=-1)


def nearest_with_ties(points, queries, n: int, rtol: float = 1e-9):
    """Each query's ``n`` nearest of ``points`` and every point tied with the ``n``-th
    (within ``rtol`` relative, for float64 positions: a fine grid's near-ties differ by
    more), so that a symmetric grid's ties are all kept rather than broken by a k-d tree's
    order. Numpy ``[P, 3]`` and ``[Q, 3]`` in; distances ``[Q, K]`` (euclidean, sorted,
    ``inf`` where a row has fewer) and indices ``[Q, K]`` out."""
    from scipy.spatial import cKDTree

    points, queries = np.asarray(points, np.float64), np.asarray(queries, np.float64)
    tree, k = cKDTree(points), min(2 * n, len(points))
    while True:
        d, j = (a.reshape(len(queries), k) for a in tree.query(queries, k=k))
        tied = d <= d[:, min(n, k) - 1:min(n, k)] * (1 + rtol) + 1e-12
        if k == len(points) or not tied[:, -1].any():
            return np.where(tied, d, np.inf), j
        k = min(2 * k, len(points))
