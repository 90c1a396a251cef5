"""Interpolation tables from an image to grid points, built once per (camera, grid).

A table is a row-normalized sparse matrix ``A [N, H*W]`` in CSR form (``crow``, ``col``,
``val``): lifting is ``x = A @ image.reshape(H*W, C)``. Bilinear and nearest tables have a
fixed number of entries per row, so lifting them is a gather.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import sparse
from scipy.spatial import ConvexHull, cKDTree

from ..cameras import Camera
from ..geometry import chord_to_geodesic, geodesic_to_chord
from .choices import METHODS


def bilinear_entries(cam: Camera, uv: np.ndarray, seen: np.ndarray):
    """Four (pixel index, weight) pairs per point; zero weights where not seen."""
    u, v = cam.sample_positions(np.where(seen, uv[:, 0], 0), np.where(seen, uv[:, 1], 0))
    j0, i0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    fu, fv = u - j0, v - i0
    i1 = np.minimum(i0 + 1, cam.height - 1)
    j1 = (j0 + 1) % cam.width if cam.wraps_u else np.minimum(j0 + 1, cam.width - 1)
    idx = np.stack([i0 * cam.width + j0, i0 * cam.width + j1, i1 * cam.width + j0,
                    i1 * cam.width + j1], 1)
    w = np.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], 1)
    return idx, w * seen[:, None]


def nearest_entries(cam: Camera, uv: np.ndarray, seen: np.ndarray):
    u, v = cam.sample_positions(np.where(seen, uv[:, 0], 0), np.where(seen, uv[:, 1], 0))
    j = np.mod(np.floor(u + 0.5).astype(np.int64), cam.width) if cam.wraps_u else \
        np.clip(np.floor(u + 0.5).astype(np.int64), 0, cam.width - 1)
    i = np.clip(np.floor(v + 0.5).astype(np.int64), 0, cam.height - 1)
    return (i * cam.width + j)[:, None], seen[:, None].astype(np.float64)


def _dense_to_csr(idx, w, n_cols):
    n, p = idx.shape
    return sparse.csr_matrix((w.ravel(), idx.ravel(), np.arange(0, n * p + 1, p)),
                             shape=(n, n_cols))


def _pixel_rays(cam: Camera):
    lnm, valid = cam.lens_normal_map()
    flat = np.flatnonzero(valid.ravel())
    return lnm.reshape(-1, 3)[flat], flat


def choose_interpolation(camera: Camera, grid) -> str:
    """``area`` when the camera's median pixel is under half the grid's spacing (the grid
    would skip pixels: aliasing), else ``bilinear`` (what the protocols lift with)."""
    om = camera.pixel_solid_angles()
    pixel = math.sqrt(float(np.median(om[om > 0])))
    return "area" if pixel < grid.spacing / 2 else "bilinear"


def check_method(method: str) -> None:
    if method not in METHODS:
        raise ValueError(f"unknown interpolation {method!r}; use one of {METHODS}")


def area_matrix(cam: Camera, pos: np.ndarray, seen: np.ndarray, uv: np.ndarray):
    """Average of every pixel whose ray falls in a point's Voronoi cell (nearest grid
    point), weighted by the pixel's solid angle. Points that receive no pixel (a grid
    finer than the image there) fall back to bilinear."""
    rays, flat = _pixel_rays(cam)
    _, owner = cKDTree(pos).query(rays)
    wpix = cam.pixel_solid_angles().ravel()[flat]
    A = sparse.csr_matrix((wpix, (owner, flat)), shape=(len(pos), cam.width * cam.height))
    A = sparse.diags(seen.astype(np.float64)) @ A
    empty = seen & (np.diff(A.indptr) == 0)
    if empty.any():
        idx, w = bilinear_entries(cam, uv, empty)
        A = A + _dense_to_csr(idx, w, A.shape[1])
    return A


def rbf_matrix(cam: Camera, pos: np.ndarray, seen: np.ndarray, sigma: float):
    """Gaussian weights exp(-d^2 / 2 sigma^2) of the lifted pixel rays within 3 sigma."""
    rays, flat = _pixel_rays(cam)
    cut = float(geodesic_to_chord(min(3 * sigma, math.pi)))
    D = cKDTree(pos[seen]).sparse_distance_matrix(cKDTree(rays), cut, output_type="coo_matrix")
    d = chord_to_geodesic(D.data)
    rows = np.flatnonzero(seen)[D.row]
    A = sparse.csr_matrix((np.exp(-0.5 * (d / sigma) ** 2), (rows, flat[D.col])),
                          shape=(len(pos), cam.width * cam.height))
    return A


def barycentric_entries(pos: np.ndarray, queries: np.ndarray, candidates: int = 8):
    """Interpolate from scattered unit vectors ``pos [N, 3]`` to ``queries [M, 3]``.

    The convex hull of ``pos`` triangulates the sphere; a query takes the barycentric
    weights of the hull face its ray exits through (gnomonic barycentric interpolation,
    exact for functions linear on the face). Returns ``(idx [M, 3], w [M, 3])``, rows of
    ``w`` summing to 1.
    """
    hull = ConvexHull(pos)
    tri, eq = hull.simplices, hull.equations  # outward normals n, offsets b (n.x + b = 0)
    cen = pos[tri].mean(1)
    _, cand = cKDTree(cen / np.linalg.norm(cen, axis=1, keepdims=True)).query(
        queries, k=min(candidates, len(tri)))
    # the ray t * q leaves the polytope through the face with the largest n.q / -b
    score = np.einsum("mkc,mc->mk", eq[cand, :3], queries) / -eq[cand, 3]
    face = cand[np.arange(len(queries)), score.argmax(1)]
    idx = tri[face]
    w = np.linalg.solve(pos[idx].transpose(0, 2, 1), queries[..., None])[..., 0]
    return idx, w / w.sum(1, keepdims=True)


def valid_pixels(cam: Camera, image_mask=None) -> np.ndarray:
    """``[H, W]`` bool: the pixels that have a ray (not past a fisheye's image circle or the
    usable field of view) and that neither the camera's :attr:`~Camera.image_mask` nor
    ``image_mask`` ignores. Every lift and re-imaging reads these pixels only."""
    ok = cam.pixels_with_rays()
    for m in (cam.image_mask, image_mask):
        if m is not None:
            ok = ok & np.asarray(m, bool)
    return ok


def valid_entries(cam: Camera, idx: np.ndarray, w: np.ndarray, image_mask=None,
                  valid: np.ndarray | None = None) -> np.ndarray:
    """The weights ``w [M, P]`` of interpolation entries (``idx [M, P]``, e.g.
    :func:`bilinear_entries`') with the pixels outside :func:`valid_pixels` (or ``valid``,
    those pixels computed before) left out and each row renormalized over the rest; a row
    with no valid pixel is all 0."""
    if valid is not None and np.shape(valid) != (cam.height, cam.width):
        raise ValueError(f"valid is {np.shape(valid)}, the camera's image {(cam.height, cam.width)}")
    ok = (valid_pixels(cam, image_mask) if valid is None else np.asarray(valid, bool)).ravel()
    if ok.all():
        return w
    w = w * ok[idx]
    total = w.sum(1, keepdims=True)
    return np.where(total > 0, w / np.where(total > 0, total, 1), 0.0)


def build_table(cam: Camera, pos: np.ndarray, method: str, image_mask=None,
                rbf_sigma: float | None = None, spacing: float | None = None) -> dict:
    """Everything the frontend needs to lift images from ``cam`` onto ``pos [N, 3]``."""
    check_method(method)
    uv, seen = cam.sees(pos)
    # pixels without a ray (past the image circle or the usable fov) never contribute
    has_ray = valid_pixels(cam, image_mask)
    image_mask = None if has_ray.all() else has_ray
    if image_mask is not None:
        m = np.asarray(image_mask, bool).ravel()
        idx, _ = nearest_entries(cam, uv, seen)
        seen &= m[idx[:, 0]]
    if not seen.any():
        raise ValueError(f"empty field of view: no grid point is visible to {cam}. Check the "
                         "camera rotation, image size and mask, or use a finer grid.")
    if method == "bilinear":
        A = _dense_to_csr(*bilinear_entries(cam, uv, seen), cam.width * cam.height)
    elif method == "nearest":
        A = _dense_to_csr(*nearest_entries(cam, uv, seen), cam.width * cam.height)
    elif method == "area":
        A = area_matrix(cam, pos, seen, uv)
    else:
        sigma = rbf_sigma if rbf_sigma is not None else 0.5 * (spacing or 0.01)
        A = rbf_matrix(cam, pos, seen, sigma)
    if image_mask is not None and method in ("area", "rbf", "bilinear"):
        A = A @ sparse.diags(np.asarray(image_mask, np.float64).ravel())
    A.sort_indices()
    rs = np.asarray(A.sum(1)).ravel()
    seen &= rs > 0
    A = sparse.diags(np.where(seen, 1 / np.where(rs > 0, rs, 1), 0.0)) @ A
    if method in ("area", "rbf"):  # bilinear/nearest keep a fixed row length for gathers
        A.eliminate_zeros()
    A.sort_indices()
    return {"crow": A.indptr.astype(np.int64), "col": A.indices.astype(np.int64),
            "val": A.data.astype(np.float64), "mask": seen,
            "uv": np.where(seen[:, None], uv, -1.0).astype(np.float32)}
