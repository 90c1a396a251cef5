import numpy as np
import pytest
import torch
from torch_geometric.data import Data
from torch_geometric.loader import DataLoader

from usf_graph import SphericalFrontend, cameras, grids
from usf_graph.data import GeodesicRadiusGraph, RandomRotation, rotate_sample
from usf_graph.frontend import GeometryCache
from usf_graph.frontend.interpolation import barycentric_entries
from usf_graph.geometry import random_rotation, rotation_from_axis_angle
from usf_graph.nn import geodesic_radius_graph

A = np.array([0.3, -0.8, 0.5])


def f(p):
    return np.exp(p @ A) + 0.3 * p[..., 0] * p[..., 2]


def pano(W=512):
    cam = cameras.Equirectangular(W, W // 2)
    lnm, _ = cam.lens_normal_map()
    return cam, f(lnm)


def test_relift_is_exact_rotation_through_rotated_camera():
    cam, img = pano()
    fe = SphericalFrontend(cam, grids.icosahedral(4), cache=GeometryCache(None))
    data = fe(img)
    data.image = torch.from_numpy(img)
    out = RandomRotation(seed=5, frontend=fe)(data.clone())
    R = random_rotation(seed=5)
    assert torch.equal(out.rotation, R.to(out.pos.dtype))
    ref = SphericalFrontend(cam.with_rotation(R.numpy() @ cam.rotation), fe.grid,
                            cache=GeometryCache(None)).lift(img)
    assert torch.equal(out.x, ref)
    p = fe.grid.pos.numpy()
    truth = f(p @ R.numpy())  # x'(p) = x(R^T p)
    assert np.abs(out.x[:, 0].double().numpy() - truth).max() < 2e-3
    assert not np.allclose(out.x[:, 0].numpy(), data.x[:, 0].numpy(), atol=0.05)
    # a dataset's sample: the picture stored per graph ([1, H, W, C]) and per-point labels,
    # which turn grid to grid as without the frontend (no labels image to re-lift exactly)
    data.image, data.y = torch.from_numpy(img)[None], torch.arange(len(fe.grid)) % 13
    out = RandomRotation(seed=5, frontend=fe)(data.clone())
    assert torch.equal(out.x, ref)
    assert torch.equal(out.y, rotate_sample(data.clone(), R).y)


def test_rotation_sequence_is_seeded():
    g = grids.icosahedral(2)
    d = lambda: SphericalFrontend(cameras.Equirectangular(64, 32), g,  # noqa: E731
                                  cache=GeometryCache(None))(np.ones((32, 64)))
    a, b, c = RandomRotation(seed=1), RandomRotation(seed=1), RandomRotation(seed=2)
    ra = [a(d()).rotation for _ in range(3)]
    rb = [b(d()).rotation for _ in range(3)]
    assert all(torch.equal(x, y) for x, y in zip(ra, rb))
    assert not torch.equal(ra[1], ra[0])
    assert not torch.equal(c(d()).rotation, ra[0])


def test_grid_to_grid_converges_at_second_order_and_identity_is_exact():
    R = random_rotation(seed=3)
    errs = []
    for level in (3, 4, 5, 6):
        g = grids.icosahedral(level)
        p = g.pos.numpy()
        data = torch.from_numpy(f(p))[:, None]
        from torch_geometric.data import Data
        out = rotate_sample(Data(x=data, pos=g.pos), R)
        errs.append(np.abs(out.x[:, 0].numpy() - f(p @ R.numpy())).max())
        if level == 3:
            same = rotate_sample(Data(x=data.clone(), pos=g.pos), torch.eye(3, dtype=torch.float64))
            assert torch.allclose(same.x, data, atol=1e-12, rtol=0)
    slope = np.polyfit(np.arange(4), np.log2(errs), 1)[0]
    assert -2.3 < slope < -1.7, (errs, slope)


def test_barycentric_weights_reproduce_queries_on_faces():
    g = grids.fibonacci(500).pos.numpy()
    q = grids.fibonacci(3001).pos.numpy()
    idx, w = barycentric_entries(g, q)
    assert (w > -1e-12).all() and np.allclose(w.sum(1), 1)
    proj = (g[idx] * w[..., None]).sum(1)  # point on the face, on the ray of q
    cos = (proj * q).sum(1) / np.linalg.norm(proj, axis=1)
    assert np.allclose(cos, 1, atol=1e-12)


def test_grid_to_grid_moves_the_mask_with_the_signal():
    cam = cameras.Fisheye(40, 63.5, 63.5, 128, 128, model="equidistant", fov_deg=180)
    g = grids.icosahedral(4)
    data = SphericalFrontend(cam, g, cache=GeometryCache(None))(np.ones((128, 128)))
    R = torch.tensor([[-1.0, 0, 0], [0, -1, 0], [0, 0, 1]], dtype=torch.float64)  # pi about z
    out = rotate_sample(data.clone(), R)
    # more than a triangle (edges up to ~0.09 rad) from the rim: whole triangles on one side
    fwd = g.pos[:, 0] > 0.12
    back = g.pos[:, 0] < -0.12
    assert data.mask[fwd].all() and not data.mask[back].any()
    assert out.mask[back].all() and not out.mask[fwd].any()
    assert (out.x[~out.mask] == 0).all()


def test_geodesic_radius_graph_transform_and_batches():
    g = grids.icosahedral(3)
    data = SphericalFrontend(cameras.Equirectangular(64, 32), g,
                             cache=GeometryCache(None))(np.ones((32, 64)))
    t = GeodesicRadiusGraph(2 * g.spacing)
    out = t(data.clone())
    ei, ew = geodesic_radius_graph(g.pos, 2 * g.spacing)
    assert torch.equal(out.edge_index, ei) and out.edge_attr.shape == (len(ew), 1)
    assert torch.allclose(out.edge_attr[:, 0].double(), ew, atol=1e-6)
    assert out.edge_attr.max() <= 2 * g.spacing + 1e-6 and "edge_weight" not in out
    batch = next(iter(DataLoader([out, out.clone()], batch_size=2)))
    again = t(batch.clone())
    assert again.edge_index.shape[1] == 2 * ei.shape[1]
    assert (batch.batch[again.edge_index[0]] == batch.batch[again.edge_index[1]]).all()
    assert repr(t).startswith("GeodesicRadiusGraph(r=")
    with pytest.raises(ValueError, match="radius"):
        GeodesicRadiusGraph(0)


def test_rotate_sample_turns_labels_and_up_with_the_signal():
    """A symmetry of the grid maps points onto points, so everything turns exactly: the
    signal and float targets resampled, integer labels permuted (not blended), up turned."""
    from usf_graph.testing import symmetry_permutation

    g = grids.icosahedral(3)
    # a fifth of a turn about an icosahedron vertex: a symmetry of the grid
    v = g.pos[0].double()
    R = torch.as_tensor(rotation_from_axis_angle(v.numpy(), 2 * np.pi / 5))
    sigma = symmetry_permutation(g.pos, R)  # R p_i = p_sigma(i)
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(len(g), 3, generator=gen, dtype=torch.float64)
    y = torch.randint(0, 13, (len(g),), generator=gen)
    depth = torch.rand(len(g), generator=gen, dtype=torch.float64)
    up = torch.tensor([[0.3, -0.2, 0.9]], dtype=torch.float64)
    out = rotate_sample(Data(x=x.clone(), y=y.clone(), pos=g.pos, up=up.clone()), R)
    want_x, want_y = torch.empty_like(x), torch.empty_like(y)
    want_x[sigma], want_y[sigma] = x, y  # x'(R p) = x(p)
    torch.testing.assert_close(out.x, want_x, atol=1e-9, rtol=0)
    assert torch.equal(out.y, want_y) and out.y.dtype == y.dtype
    torch.testing.assert_close(out.up, up @ R.T)
    dep = rotate_sample(Data(x=x.clone(), y=depth.clone(), pos=g.pos), R).y  # a float target
    want = torch.empty_like(depth)
    want[sigma] = depth
    torch.testing.assert_close(dep, want, atol=1e-9, rtol=0)
    # with a field of view: the mask turns too; hidden points are 0 and their labels ignored
    mask = torch.rand(len(g), generator=gen) > 0.4
    out = rotate_sample(Data(x=x.clone(), y=y.clone(), pos=g.pos, mask=mask.clone()), R,
                        ignore_index=255)
    want_m = torch.empty_like(mask)
    want_m[sigma] = mask
    assert torch.equal(out.mask, want_m) and out.x.shape == x.shape and out.y.shape == y.shape
    torch.testing.assert_close(out.x, want_x * want_m[:, None], atol=1e-9, rtol=0)
    assert torch.equal(out.y, torch.where(want_m, want_y, 255))


def test_rotate_sample_labels_match_the_room_seen_turned():
    """Labels of a rendered room, turned grid to grid, against the room's exact labels seen
    from the turned frame: equal but on the boundaries between objects; a cap's mask
    moves with them, and what it turns out of view is ignored."""
    from usf_graph.data.transforms import IGNORE_LABEL
    from usf_graph.datasets.rooms import grid_labels
    from usf_graph.scenes import IGNORE, make_room

    assert IGNORE_LABEL == IGNORE
    g = grids.icosahedral(5)
    pos = g.pos.double().numpy()
    scene = make_room(seed=3, index=3, materials="by_kind")
    position, RA = scene.viewpoint(0)
    Q = random_rotation(seed=4).numpy()
    cap = torch.as_tensor(pos @ np.array([1.0, 0.0, 0.0]) > 0.2)  # a 156-degree field of view
    ya = torch.as_tensor(grid_labels(scene, position, RA, pos, cap.numpy()))
    yb = grid_labels(scene, position, RA @ Q.T, pos, np.ones(len(pos), bool))  # world = RA Q^T p
    out = rotate_sample(Data(x=torch.zeros(len(pos), 1), y=ya, pos=g.pos, mask=cap), torch.as_tensor(Q))
    seen = out.mask.numpy()
    assert 0.2 < seen.mean() < 0.5 and (out.y.numpy()[~seen] == IGNORE).all()
    agree = (out.y.numpy()[seen] == yb[seen]).mean()
    assert agree > 0.95, agree
    # labels with several columns per point (multi-label) turn and hide alike
    multi = rotate_sample(Data(x=torch.zeros(len(pos), 1), y=torch.stack([ya, ya], -1), pos=g.pos,
                               mask=cap), torch.as_tensor(Q)).y
    assert torch.equal(multi, torch.stack([out.y, out.y], -1))
    with pytest.raises(ValueError, match="rotate_boxes"):
        rotate_sample(Data(x=torch.zeros(len(pos), 1), pos=g.pos, boxes=torch.zeros(1, 5)), Q)


def test_level_turns_a_sample_so_that_its_up_is_z():
    """Level: the smallest turn taking data.up to +z, applied like RandomRotation's (the
    signal re-lifted through the camera mounted turned, labels and up with it)."""
    from usf_graph.data import Level
    from usf_graph.geometry import level_rotation

    cam, img = pano()
    fe = SphericalFrontend(cam, grids.icosahedral(4), cache=GeometryCache(None))
    u = torch.nn.functional.normalize(torch.tensor([[0.2, -0.3, 0.93]], dtype=torch.float64), dim=-1)
    data = fe(img)
    data.image, data.up, data.y = torch.from_numpy(img)[None], u.clone(), torch.arange(len(fe.grid)) % 13
    out = Level(frontend=fe)(data.clone())
    R = level_rotation(u[0].numpy())
    torch.testing.assert_close(out.up[0], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), atol=1e-12, rtol=0)
    torch.testing.assert_close(out.rotation, torch.as_tensor(R).to(out.pos.dtype))
    ref = SphericalFrontend(cam.turned(R), fe.grid, cache=GeometryCache(None)).lift(img)
    assert torch.equal(out.x, ref)
    assert torch.equal(out.y, rotate_sample(data.clone(), torch.as_tensor(R)).y)
    grid_to_grid = Level()(data.clone())  # without the frontend: resampled, up still +z
    assert (grid_to_grid.x - ref).abs().max() < 0.05 and torch.allclose(grid_to_grid.up, out.up)
    with pytest.raises(ValueError, match="needs data.up"):
        Level()(fe(img))
    assert repr(Level(fe)) == "Level(re-lift)"
