import numpy as np
import pytest
import torch
from torch_geometric.loader import DataLoader

from usf_graph import SphericalFrontend, cameras, grids
from usf_graph.data import GeodesicRadiusGraph, RandomRotation, rotate_sample
from usf_graph.frontend import GeometryCache
from usf_graph.frontend.interpolation import barycentric_entries
from usf_graph.geometry import random_rotation
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
