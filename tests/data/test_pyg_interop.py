"""Mixing our layers with PyG's: distances live in edge_attr, affinities are explicit, and
unseen points can be dropped, on a batch from two different cameras."""

import numpy as np
import pytest
import torch
from torch_geometric.loader import DataLoader
from torch_geometric.nn import GATConv, GCNConv, global_mean_pool

from usf_graph import cameras, grids
from usf_graph.data import GaussianEdgeWeight, VisibleSubgraph
from usf_graph.frontend import GeometryCache, SphericalFrontend
from usf_graph.geometry import geodesic_distance
from usf_graph.nn import SphericalConv


@pytest.fixture(scope="module")
def two_cameras():
    g = grids.icosahedral(3)
    cache = GeometryCache(None)
    fish = SphericalFrontend(cameras.KannalaBrandt(60, 60, 63.5, 47.5, 128, 96, fov_deg=190), g,
                             cache=cache)
    pin = SphericalFrontend(cameras.Pinhole(80, 80, 47.5, 35.5, 96, 72), g, cache=cache)
    return fish, pin


def images(fe_list, seed):
    rng = np.random.default_rng(seed)
    return [rng.random((fe.camera.height, fe.camera.width, 3)) for fe in fe_list]


class Mixed(torch.nn.Module):
    def __init__(self, radius):
        super().__init__()
        self.sph = SphericalConv(3, 8, radius)
        self.gcn = GCNConv(8, 8)
        self.gat = GATConv(8, 4, heads=2, edge_dim=1)

    def forward(self, d):
        h = torch.relu(self.sph(d.x, d.edge_index, d.edge_attr, node_weight=d.area))
        h = torch.relu(self.gcn(h, d.edge_index, d.edge_weight))
        h = self.gat(h, d.edge_index, d.edge_attr)
        return global_mean_pool(h, d.batch)


def prepare(data):
    return GaussianEdgeWeight()(VisibleSubgraph()(data))


def test_spherical_image_keeps_distances_out_of_edge_weight(two_cameras):
    fe = two_cameras[0]
    img = fe(images([fe], 0)[0])
    assert "edge_weight" not in img and img.edge_attr.shape == (img.edge_index.shape[1], 1)
    d = geodesic_distance(img.pos[img.edge_index[0]].double(), img.pos[img.edge_index[1]].double())
    torch.testing.assert_close(img.edge_dist.double(), d, atol=1e-6, rtol=0)
    w = GaussianEdgeWeight(sigma=0.1)(img.clone()).edge_weight
    torch.testing.assert_close(w, torch.exp(-0.5 * (img.edge_dist / 0.1) ** 2))
    loops = img.edge_index[0] == img.edge_index[1]
    assert (w[loops] == 1).all() and (w > 0).all() and (w[~loops] < 1).all()
    with pytest.raises(ValueError, match="edge_attr"):
        GaussianEdgeWeight()(img.clone().update({"edge_attr": None}))


def test_mixed_model_on_a_batch_from_two_cameras(two_cameras):
    torch.manual_seed(0)
    torch.set_default_dtype(torch.float64)
    try:
        fes = list(two_cameras)
        imgs = [fe(im).to_dict() for fe, im in zip(fes, images(fes, 1))]
        data = [prepare(fes[0].image(imgs[0]["x"].double())),
                prepare(fes[1].image(imgs[1]["x"].double()))]
        for d, fe in zip(data, fes):  # only the visible points, distances still right
            assert d.num_nodes == int(fe.mask.sum()) and d.mask.all()
            dd = geodesic_distance(d.pos[d.edge_index[0]], d.pos[d.edge_index[1]])
            torch.testing.assert_close(d.edge_attr[:, 0], dd, atol=1e-12, rtol=0)
        model = Mixed(2 * fes[0].grid.spacing)
        batch = next(iter(DataLoader(data, batch_size=2)))
        out = model(batch)
        assert out.shape == (2, 8) and torch.isfinite(out).all()
        for i, d in enumerate(data):  # each graph alone gives the same answer
            alone = next(iter(DataLoader([d], batch_size=1)))
            torch.testing.assert_close(model(alone)[0], out[i], atol=1e-12, rtol=0)
        out.sum().backward()
        assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in model.parameters())
        # what unseen points hold cannot matter once they are dropped ...
        noisy = fes[1].image(imgs[1]["x"].double() + 5.0 * (~fes[1].mask)[:, None])
        again = next(iter(DataLoader([data[0], prepare(noisy)], batch_size=2)))
        torch.testing.assert_close(model(again), out, atol=1e-12, rtol=0)
        # ... while a PyG layer on the whole sphere mixes them in (the trap this avoids)
        full = GaussianEdgeWeight()(fes[1].image(imgs[1]["x"].double()))
        full_noisy = GaussianEdgeWeight()(noisy.clone())
        gcn = GCNConv(3, 4)
        seen = fes[1].mask
        a = gcn(full.x, full.edge_index, full.edge_weight)[seen]
        b = gcn(full_noisy.x, full_noisy.edge_index, full_noisy.edge_weight)[seen]
        assert (a - b).abs().max() > 1e-3
    finally:
        torch.set_default_dtype(torch.float32)


def test_visible_subgraph_errors(two_cameras):
    img = two_cameras[1](images([two_cameras[1]], 2)[0])
    with pytest.raises(ValueError, match="all False"):
        VisibleSubgraph()(img.clone().update({"mask": torch.zeros_like(img.mask)}))
    with pytest.raises(ValueError, match="needs data.mask"):
        VisibleSubgraph()(img.clone().update({"mask": None}))


@pytest.mark.parametrize("layer", ["gcn", "gat"])
def test_pyg_layers_on_distance_affinities_are_equivariant(layer):
    """PyG's layers read the graph and its affinities only, so they keep the grid's exact
    symmetries (HEALPix maps onto itself under 90 degrees about z), in float64."""
    import math

    from usf_graph.geometry import rotation_from_axis_angle
    from usf_graph.nn import geodesic_radius_graph
    from usf_graph.testing import assert_equivariant

    hp = grids.healpix(4)
    ei, ew = geodesic_radius_graph(hp.pos, 1.7 * hp.spacing)
    w = torch.exp(-0.5 * (ew / hp.spacing) ** 2)
    torch.manual_seed(0)
    conv = (GCNConv(3, 5) if layer == "gcn" else GATConv(3, 5, heads=2, edge_dim=1)).double()
    fn = (lambda x: conv(x, ei, w)) if layer == "gcn" else (lambda x: conv(x, ei, w[:, None]))
    R = rotation_from_axis_angle(torch.tensor([0.0, 0, 1], dtype=torch.float64),
                                 torch.tensor(math.pi / 2, dtype=torch.float64))
    x = torch.randn(len(hp), 3, dtype=torch.float64)
    assert fn(x).shape == (len(hp), 5 if layer == "gcn" else 10)
    assert assert_equivariant(fn, x, hp.pos, R, atol=1e-10) < 1e-10
    with pytest.raises(AssertionError):  # the check can fail: a layer that reads pos is not
        assert_equivariant(lambda x: fn(x) + hp.pos[:, :1], x, hp.pos, R, atol=1e-10)
