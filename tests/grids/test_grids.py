import math

import numpy as np
import pytest
import torch

from usf_graph import grids
from usf_graph.geometry import geodesic_distance, random_rotation, rotate
from usf_graph.grids import base
from usf_graph.grids.base import Grid, grid_size


@pytest.mark.parametrize("g, n", [(lambda: grids.icosahedral(3), 642),
                                  (lambda: grids.healpix(8), 768),
                                  (lambda: grids.healpix(8, nest=False), 768),
                                  (lambda: grids.fibonacci(1000), 1000),
                                  (lambda: grids.equiangular(20, 40), 800)])
def test_counts_areas_and_coarsening(g, n):
    g = g()
    assert len(g) == n and g.pos.dtype == torch.float64
    torch.testing.assert_close(g.pos.norm(dim=1), torch.ones(n, dtype=torch.float64))
    assert abs(float(g.area.sum()) - 4 * math.pi) < 1e-9
    coarse, cl = g.coarsen()
    assert cl.shape == (n,) and cl.dtype == torch.long
    assert int(cl.min()) == 0 and int(cl.max()) == len(coarse) - 1
    assert torch.unique(cl).numel() == len(coarse)  # every cluster is used
    # each fine point's cluster is (one of) its nearest coarse point(s)
    d_all = geodesic_distance(g.pos[:, None], coarse.pos[None])
    d_own = d_all[torch.arange(n), cl]
    assert (d_own <= d_all.min(1).values + 1e-12).all()


def test_hierarchy_is_the_chain_of_coarsenings():
    chain = grids.icosahedral(4).hierarchy(3)
    assert [len(g) for g, _ in chain] == [642, 162, 42]
    fine = grids.icosahedral(4)
    for coarse, cluster in chain:
        want_grid, want_cluster = fine.coarsen()
        assert coarse.spec == want_grid.spec and torch.equal(cluster, want_cluster)
        assert len(cluster) == len(fine)
        fine = coarse
    with pytest.raises(ValueError, match="cannot be coarsened further"):
        grids.icosahedral(1).hierarchy(2)


def test_icosahedral_is_nested():
    for level in range(1, 5):
        fine, coarse = grids.icosahedral(level), grids.icosahedral(level - 1)
        assert len(fine) == 10 * 4 ** level + 2
        torch.testing.assert_close(fine.pos[:len(coarse)], coarse.pos, rtol=0, atol=0)


def _ring_scheme(nside):
    """HEALPix RING centres from Gorski et al. (2005), eqs. 4-9, written independently."""
    z, phi = [], []
    for i in range(1, 4 * nside):
        if i < nside:
            for j in range(1, 4 * i + 1):
                z.append(1 - i * i / (3 * nside * nside))
                phi.append(math.pi / (2 * i) * (j - 0.5))
        elif i <= 3 * nside:
            shift = 1.0 if (i + nside) % 2 else 0.5  # rings alternate their phase
            for j in range(1, 4 * nside + 1):
                z.append(4 / 3 - 2 * i / (3 * nside))
                phi.append(math.pi / (2 * nside) * (j - shift))
        else:
            k = 4 * nside - i
            for j in range(1, 4 * k + 1):
                z.append(-(1 - k * k / (3 * nside * nside)))
                phi.append(math.pi / (2 * k) * (j - 0.5))
    z, phi = np.array(z), np.array(phi)
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)


def _nest_scheme(nside):
    """NESTED centres from the (face, x, y) bit-interleaved index, written independently."""
    jrll = [2, 2, 2, 2, 3, 3, 3, 3, 4, 4, 4, 4]
    jpll = [1, 3, 5, 7, 0, 2, 4, 6, 1, 3, 5, 7]
    out = []
    for p in range(12 * nside * nside):
        face, ipf = divmod(p, nside * nside)
        ix = sum(((ipf >> (2 * b)) & 1) << b for b in range(16))
        iy = sum(((ipf >> (2 * b + 1)) & 1) << b for b in range(16))
        jr = jrll[face] * nside - ix - iy - 1
        if jr < nside:
            nr, z, ks = jr, 1 - jr * jr / (3 * nside * nside), 0
        elif jr > 3 * nside:
            nr = 4 * nside - jr
            z, ks = nr * nr / (3 * nside * nside) - 1, 0
        else:
            nr, z, ks = nside, (2 * nside - jr) * 2 / (3 * nside), (jr - nside) & 1
        jp = (jpll[face] * nr + ix - iy + 1 + ks) / 2
        jp = jp - 4 * nside if jp > 4 * nside else (jp + 4 * nside if jp < 1 else jp)
        phi = (jp - (ks + 1) * 0.5) * (math.pi / 2 / nr)
        r = math.sqrt(1 - z * z)
        out.append([r * math.cos(phi), r * math.sin(phi), z])
    return np.array(out)


@pytest.mark.parametrize("nside", [1, 2, 4, 8])
def test_healpix_matches_the_published_scheme(nside):
    np.testing.assert_allclose(grids.healpix(nside, nest=False).pos.numpy(), _ring_scheme(nside),
                               atol=1e-12)
    np.testing.assert_allclose(grids.healpix(nside, nest=True).pos.numpy(), _nest_scheme(nside),
                               atol=1e-12)
    if nside > 1:
        _, cl = grids.healpix(nside).coarsen()
        assert torch.equal(cl, torch.arange(12 * nside * nside) // 4)


def test_grid_quality_ordering():
    ico, hp = grids.icosahedral(4), grids.healpix(16)
    fib, eq = grids.fibonacci(2562), grids.equiangular(36, 72)
    q = {g.name: g.quality() for g in (ico, hp, fib, eq)}
    assert q["healpix"]["area_cv"] < 1e-12  # equal-area by construction
    assert q["icosahedral"]["nbr6_dist_cv"] < min(q[k]["nbr6_dist_cv"] for k in ("healpix", "fibonacci", "equiangular"))
    assert q["equiangular"]["area_cv"] > 0.3


def test_spec_round_trip_and_errors():
    assert len(grids.from_spec("icosahedral:2")) == 162
    assert grids.from_spec("healpix:4,ring").params == {"nside": 4, "nest": False}
    assert len(grids.from_spec("equiangular:8,16")) == 128
    with pytest.raises(ValueError, match="unknown grid"):
        grids.from_spec("cube:3")
    for g in (grids.icosahedral(2), grids.healpix(4), grids.healpix(4, nest=False),
              grids.fibonacci(100), grids.equiangular(8, 16)):  # a grid's own spec reads back
        back = grids.from_spec(g.spec)
        assert back.params == g.params and torch.equal(back.pos, g.pos), g.spec
    nested = [grids.from_spec(f"healpix:4{o}").params for o in ("", ",nest", ",nested", ",NEST", ",true")]
    assert nested == [{"nside": 4, "nest": True}] * 5
    assert grids.from_spec("healpix:4,false").params == {"nside": 4, "nest": False}
    for bad in ("healpix:4,rnig", "healpix:4,ring,2", "healpix:"):  # a typo picks no ordering
        with pytest.raises(ValueError, match=f"bad grid spec '{bad}'"):
            grids.from_spec(bad)
    with pytest.raises(ValueError, match="power of two"):
        grids.healpix(3)
    with pytest.raises(ValueError, match="cannot be coarsened"):
        grids.icosahedral(0).coarsen()
    for bad, match in ((lambda: grids.icosahedral(2.5), r"integer in \[0, 10\], got 2.5"),
                       (lambda: grids.icosahedral(11), "got 11"),
                       (lambda: grids.healpix(0), "nside must be an integer >= 1"),
                       (lambda: grids.healpix(4.5), "got 4.5"),
                       (lambda: grids.fibonacci(3), "n must be an integer >= 4"),
                       (lambda: grids.fibonacci("100"), "got '100'"),
                       (lambda: grids.equiangular(8, 1), "nlon must be")):
        with pytest.raises(ValueError, match=match):
            bad()
    assert len(grids.fibonacci(100.0)) == 100  # an integral float is fine


def test_rotation_preserves_spacing():
    g = grids.icosahedral(3)
    R = random_rotation(seed=1)
    d = geodesic_distance(rotate(g.pos[:5], R), rotate(g.pos[5:10], R))
    torch.testing.assert_close(d, geodesic_distance(g.pos[:5], g.pos[5:10]))


def test_locality_order_lets_the_convolution_tile():
    from usf_graph.nn import EdgePlan, geodesic_radius_graph

    g = grids.icosahedral(3)
    order = grids.locality_order(g.pos)
    assert sorted(order.tolist()) == list(range(len(g)))

    def plan(pos):  # blocks of 64 rows; one tile when their halos add up to > 2 N
        ei, _ = geodesic_radius_graph(pos, 1.6 * g.spacing)
        return EdgePlan(ei, len(g), tile_rows=64)

    local = plan(g.pos[order])
    assert len(local.bounds) == 11
    assert sum(len(getattr(local, f"cols{t}")) for t in range(11)) < 2 * len(g)
    assert len(plan(g.pos).bounds) == 1  # the nested numbering has no locality


def test_voronoi_areas_are_kept_by_the_points_not_the_object(monkeypatch):
    """A new grid object with the same points reuses their areas; other points (a turned
    grid) get their own, and editing a grid's areas leaves the kept ones alone."""
    calls = []
    real = base.voronoi_areas
    monkeypatch.setattr(base, "voronoi_areas", lambda p: calls.append(len(p)) or real(p))
    monkeypatch.setattr(base, "_AREAS", type(base._AREAS)())
    a = grids.fibonacci(300).area
    b = grids.fibonacci(300).area
    assert len(calls) == 1 and torch.equal(a, b) and abs(float(a.sum()) - 4 * math.pi) < 1e-9
    a.mul_(2)  # the caller's copy
    assert torch.equal(grids.fibonacci(300).area, b) and len(calls) == 1
    turned = rotate(grids.fibonacci(300).pos, random_rotation(seed=1, dtype=torch.float64))
    other = grids.Grid(turned, "fibonacci", {"n": 300})  # same name, other points
    assert torch.equal(other.area, torch.as_tensor(real(other.pos.numpy()))) and len(calls) == 2


def test_smallest_grids_refusals_spacing_and_quality_against_brute_force():
    """The smallest grid of each kind builds; a grid normalizes its points and refuses
    fewer than 4; ``spacing`` and ``quality()`` are the nearest-neighbour statistics they
    say, computed here from every pairwise distance."""
    for g, n in ((grids.icosahedral(0), 12), (grids.healpix(1), 12), (grids.fibonacci(4), 4),
                 (grids.equiangular(2, 2), 4)):
        assert len(g) == n, g.spec
    for pos in (np.eye(3), np.ones((5, 2))):
        with pytest.raises(ValueError, match=r"a grid needs \[N >= 4, 3\] points, got"):
            Grid(pos, "points", {})
    with pytest.raises(ValueError, match="got None"):
        grids.fibonacci(None)
    g = Grid(2.5 * grids.fibonacci(60).pos.numpy(), "points", {})
    torch.testing.assert_close(g.pos.norm(dim=1), torch.ones(60, dtype=torch.float64))
    d = geodesic_distance(g.pos[:, None], g.pos[None]).numpy()
    np.fill_diagonal(d, np.inf)
    d = np.sort(d, 1)
    nn, six = d[:, 0], d[:, :6]
    assert abs(g.spacing - nn.mean()) < 1e-12
    q = g.quality()
    assert abs(q["nn_dist_cv"] - nn.std() / nn.mean()) < 1e-9
    assert abs(q["nbr6_dist_cv"] - six.std() / six.mean()) < 1e-9
    assert abs(q["spacing_deg"] - math.degrees(nn.mean())) < 1e-9


def test_equiangular_is_an_equirectangular_image_the_right_way_round():
    """Point ``i * W + j`` is the panorama's pixel (row i, column j): text lifted from
    the image by nearest neighbour and reshaped to ``[H, W]`` is the image, so it reads
    left to right (a grid numbered by increasing longitude gave it mirrored)."""
    import cv2

    from usf_graph.cameras import Equirectangular
    from usf_graph.frontend import SphericalFrontend

    h, w = 24, 64
    g, cam = grids.equiangular(h, w), Equirectangular(w, h)
    rays, ok = cam.lens_normal_map()
    assert ok.all()
    np.testing.assert_allclose(g.pos.numpy(), rays.reshape(-1, 3), rtol=0, atol=1e-12)
    image = np.zeros((h, w), np.uint8)
    cv2.putText(image, "usf", (4, 19), cv2.FONT_HERSHEY_SIMPLEX, 0.7, 255, 2)
    lifted = SphericalFrontend(cam, g, interpolation="nearest")(image)
    assert lifted.mask.all()
    got = lifted.x[:, 0].reshape(h, w).numpy()
    np.testing.assert_array_equal(got, image)
    assert image[:, : w // 3].any() and not np.array_equal(image, image[:, ::-1])


def test_fibonacci_points_climb_the_golden_spiral():
    """z_i = 1 - (2i + 1) / n, and each point turns by the golden angle 2 pi / phi^2
    (137.5 degrees) about the z axis from the one before."""
    n = 50
    p = grids.fibonacci(n).pos.numpy()
    np.testing.assert_allclose(p[:, 2], 1 - (2 * np.arange(n) + 1) / n, rtol=0, atol=1e-15)
    phi = (1 + math.sqrt(5)) / 2
    step = np.mod(np.diff(np.arctan2(p[:, 1], p[:, 0])), 2 * math.pi)
    np.testing.assert_allclose(step, 2 * math.pi / phi ** 2, rtol=0, atol=1e-12)
    assert math.isclose(math.degrees(2 * math.pi / phi ** 2), 137.50776405, abs_tol=1e-8)


def test_each_kind_coarsens_to_its_own_next_grid_and_the_coarsest_refuses():
    for fine, want in ((grids.icosahedral(2), {"level": 1}),
                       (grids.healpix(4), {"nside": 2, "nest": True}),
                       (grids.healpix(4, nest=False), {"nside": 2, "nest": False}),
                       (grids.fibonacci(16), {"n": 4}),
                       (grids.fibonacci(103), {"n": 25}),
                       (grids.equiangular(4, 4), {"nlat": 2, "nlon": 2}),
                       (grids.equiangular(6, 20), {"nlat": 3, "nlon": 10})):
        coarse, cluster = fine.coarsen()
        assert coarse.name == fine.name and coarse.params == want, fine.spec
        assert len(cluster) == len(fine)
    for g in (grids.healpix(1), grids.fibonacci(15), grids.equiangular(3, 8),
              grids.equiangular(8, 3)):
        with pytest.raises(ValueError, match="cannot be coarsened further"):
            g.coarsen()


@pytest.mark.parametrize("level", [0, 1, 2, 3])
def test_icosahedral_grid_has_the_icosahedrons_symmetry(level):
    """Turns of 72 degrees about a vertex and 120 degrees about a face's centre map every
    level onto itself; at level 0 each vertex's neighbours lie at arctan 2 (63.4 degrees),
    five of them, then five at 180 - arctan 2 and one opposite."""
    from scipy.spatial.transform import Rotation

    g = grids.icosahedral(level)
    p = g.pos.numpy()
    if level == 0:
        d = np.sort(np.degrees(geodesic_distance(g.pos[:, None], g.pos[None]).numpy()), 1)
        near = math.degrees(math.atan(2))
        want = [0.0] + [near] * 5 + [180 - near] * 5 + [180.0]
        np.testing.assert_allclose(d, np.tile(want, (12, 1)), rtol=0, atol=1e-6)
    face = grids.icosahedral_faces(0)[0]
    centre = p[face].sum(0)
    for axis, angle in ((p[0], 72.0), (centre, 120.0), (p[5], 144.0)):
        turned = Rotation.from_rotvec(np.radians(angle) * axis / np.linalg.norm(axis)).apply(p)
        gap = np.linalg.norm(turned[:, None] - p[None], axis=-1).min(1)
        assert gap.max() < 1e-12, (axis, angle)


def test_the_kept_areas_are_the_last_16_point_sets(monkeypatch):
    monkeypatch.setattr(base, "_AREAS", type(base._AREAS)())
    sets = [grids.fibonacci(20 + k) for k in range(17)]
    for g in sets:
        torch.testing.assert_close(g.area, torch.as_tensor(base.voronoi_areas(g.pos.numpy())))
    assert len(base._AREAS) == 16
    grids.fibonacci(21).area  # noqa: B018 - a hit makes set 1 the most recent: set 2 goes next
    grids.fibonacci(50).area  # noqa: B018
    kept = {len(v) for v in base._AREAS.values()}
    assert 20 not in kept and 21 in kept and 22 not in kept and 50 in kept


def test_grid_sizes_include_both_bounds():
    assert grid_size("level", 10, 0, 10) == 10 and grid_size("level", 0, 0, 10) == 0
    with pytest.raises(ValueError, match=r"level must be an integer in \[0, 10\], got 11"):
        grid_size("level", 11, 0, 10)
