"""Point-cloud datasets: OFF files, ModelNet's layout, procedural shapes."""

import math

import numpy as np
import pytest
import torch

from usf_graph.datasets import SHAPES, ModelNet, ProceduralShapes, read_off, sample_surface
from usf_graph.datasets.pointcloud import make_shape

FIX = "tests/fixtures/modelnet"


def test_read_off_standard_and_malformed_header():
    v, f = read_off(f"{FIX}/ModelNet10/chair/train/chair_0001.off")
    assert v.shape == (8, 3) and f.shape == (12, 3)  # 6 quads fanned into 12 triangles
    v, f = read_off(f"{FIX}/ModelNet10/table/train/table_0001.off")  # "OFF4 4 0"
    assert v.shape == (4, 3) and f.shape == (4, 3) and v[3, 2] == 2
    p = sample_surface(*read_off(f"{FIX}/ModelNet10/chair/train/chair_0001.off"), 4000,
                       np.random.default_rng(0))
    on_face = np.isclose(p, 0) | np.isclose(p, 1)
    assert on_face.any(1).all() and ((p >= -1e-12) & (p <= 1 + 1e-12)).all()
    # area weighting: each of the 6 unit faces gets about 1/6 of the points
    counts = np.array([np.isclose(p[:, a], s).sum() for a in range(3) for s in (0, 1)])
    assert np.abs(counts / 4000 - 1 / 6).max() < 0.03


@pytest.mark.parametrize("text, msg", [
    ("", "OFF header"), ("PLY\n", "OFF header"), ("OFF\n", "counts"),
    ("OFF\nthree 1 0\n", "counts"), ("OFF\n3 1 0\n0 0 0\n1 0 0\n", "truncated"),
    ("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n", "outside"),
    ("OFF\n3 1 0\n0 0 0\n1 0 x\n0 1 0\n3 0 1 2\n", "malformed"),
    ("OFF\n3 1 0\n0 0 0\n1 0 nan\n0 1 0\n3 0 1 2\n", "finite"),
])
def test_read_off_rejects_corrupt_files(tmp_path, text, msg):
    p = tmp_path / "bad.off"
    p.write_text(text)
    with pytest.raises(ValueError, match=msg):
        read_off(p)


def test_modelnet_dataset_reads_the_official_layout(tmp_path):
    import shutil

    shutil.copytree(FIX, tmp_path, dirs_exist_ok=True)
    train = ModelNet(tmp_path, "10", "train", num_points=64)
    assert train.classes == ["chair", "table"] and train.y.tolist() == [0, 1, 1]
    assert train.pos.shape == (3, 64, 3) and train[2].pos.shape == (64, 3)
    assert ModelNet(tmp_path, "10", "test", num_points=64).y.tolist() == [0, 1]
    again = ModelNet(tmp_path, "10", "train", num_points=64)  # from processed/
    assert torch.equal(again.pos, train.pos)
    torch.save({"pos": train.pos}, train.processed_paths[0])  # a stale file, lacking y: made again
    with pytest.warns(UserWarning, match=r"missing \['classes', 'y'\].*processing it again"):
        remade = ModelNet(tmp_path, "10", "train", num_points=64)
    assert torch.equal(remade.pos, train.pos) and remade.y.tolist() == [0, 1, 1]
    with pytest.raises(FileNotFoundError, match="ModelNet40"):
        ModelNet(tmp_path / "empty", "40")
    from torch_geometric.transforms import FixedPoints, NormalizeScale

    shutil.copytree(FIX, tmp_path / "n", dirs_exist_ok=True)
    norm = ModelNet(tmp_path / "n", "10", "train", num_points=64, pre_transform=NormalizeScale())
    centred = train.pos - train.pos.mean(1, keepdim=True)
    scale = centred.abs().amax((1, 2), keepdim=True)
    torch.testing.assert_close(norm.pos, centred / scale, rtol=0, atol=1e-5)
    shutil.copytree(FIX, tmp_path / "f", dirs_exist_ok=True)
    fewer = ModelNet(tmp_path / "f", "10", "train", num_points=64, pre_transform=FixedPoints(16))
    assert fewer.pos.shape == (3, 16, 3)


def test_procedural_shapes_are_deterministic_and_labelled():
    a, b = ProceduralShapes("train", 2, 128, seed=3), ProceduralShapes("train", 2, 128, seed=3)
    assert torch.equal(a.pos, b.pos) and len(a) == 2 * len(SHAPES)
    assert not torch.equal(a.pos, ProceduralShapes("test", 2, 128, seed=3).pos)
    sphere = a.pos[0].double()
    r = sphere.norm(dim=1)
    assert (r.std() / r.mean()) < 0.03  # noisy sphere of one radius
    assert a.part[a.y == SHAPES.index("cube")].all() and not a.part[a.y == 0].any()
    cyl = a.part[a.y == SHAPES.index("cylinder")].float().mean()
    assert 0.1 < cyl < 0.4  # caps are a minority of a cylinder's area


def _share(hit, p):
    """A binomial share of ``hit`` equal to ``p`` within 5 standard deviations."""
    assert abs(hit.mean() - p) <= 5 * math.sqrt(p * (1 - p) / hit.size), (hit.mean(), p)


def _round(p):
    """Points spread evenly about the z axis (a quarter in each quadrant) and drawn from a
    continuum in height (no two alike)."""
    quadrant = (p[:, 0] > 0) * 2 + (p[:, 1] > 0)
    for k in range(4):
        _share(quadrant == k, 1 / 4)
    assert len(np.unique(p[:, 2])) == len(p) or np.ptp(p[:, 2]) == 0


def _disc(p, radius):
    """A flat disc of ``radius`` sampled by area: even about z, a quarter within radius / 2."""
    _round(p)
    _share(np.hypot(p[:, 0], p[:, 1]) < radius / 2, 1 / 4)


def _surface(name, p, part):
    """Check that noise-free points of a shape at scale 1 lie on its surface (to rounding)
    and are spread by area; return its jittered proportions, each fitted from the points."""
    x, y, z = p.T
    rho = np.hypot(x, y)
    flat = part == 1
    if name == "sphere":
        np.testing.assert_allclose(np.linalg.norm(p, axis=1), 1, atol=1e-12)
        assert not flat.any()
        return {}
    if name == "ellipsoid":  # x^2 + y^2 / b^2 + z^2 / c^2 = 1, solved for 1 / b^2, 1 / c^2
        inv, *_ = np.linalg.lstsq(np.stack([y ** 2, z ** 2], 1), 1 - x ** 2, rcond=None)
        np.testing.assert_allclose(x ** 2 + y ** 2 * inv[0] + z ** 2 * inv[1], 1, atol=1e-9)
        assert not flat.any() and abs(x).max() > 0.99
        return {"b": inv[0] ** -0.5, "c": inv[1] ** -0.5}
    if name in ("cube", "plate"):  # every point on a face; faces drawn by area
        half = abs(p).max(0)
        assert half[0] == 1 and flat.all() and (name == "plate" or (half == 1).all())
        face = np.argmax(abs(p) / half, 1)
        np.testing.assert_allclose(abs(p[np.arange(len(p)), face]), half[face], rtol=1e-12)
        assert (abs(p) <= half + 1e-12).all()
        area = np.array([half[1] * half[2], half[0] * half[2], half[0] * half[1]])
        for k in range(3):
            for sign in (-1, 1):
                _share((face == k) & (np.sign(p[:, k]) == sign), area[k] / area.sum() / 2)
        return {"b": half[1], "c": half[2]}
    if name == "cylinder":
        r, h = rho.max(), abs(z).max()
        np.testing.assert_allclose(rho[~flat], r, rtol=1e-12)
        np.testing.assert_allclose(abs(z[flat]), h, rtol=1e-12)
        assert (abs(z) <= h).all() and (rho <= r + 1e-12).all()
        for cap in (-1, 1):
            _share(flat & (np.sign(z) == cap), r / (2 * h + r) / 2)
            _disc(p[flat & (np.sign(z) == cap)], r)
        _round(p[~flat])
        _share(~flat & (z > 0), h / (2 * h + r))  # the side, uniform along its height
        return {"r": r, "h": h}
    if name == "cone":  # base disc at z = -h, radius shrinking linearly to the apex at +h
        h = -z.min()
        np.testing.assert_allclose(z[flat], -h, rtol=1e-12)
        slope, mid = np.polyfit(z[~flat], rho[~flat], 1)
        np.testing.assert_allclose(rho[~flat], mid + slope * z[~flat], atol=1e-9)
        assert abs(mid + slope * h) < 1e-9 and (rho[flat] <= mid - slope * h).all()
        r = mid - slope * h
        side = math.hypot(r, 2 * h)
        _share(flat, r / (r + side))
        _disc(p[flat], r)
        _round(p[~flat])
        _share(~flat & (z > 0), side / (r + side) / 4)  # the top half has a quarter of the side's area
        return {"r": r, "h": h}
    if name == "capsule":  # a band of radius r over z in [-h, h], and a hemisphere at each end
        r = rho.max()
        band = rho > r - 1e-9
        centre = abs(z) - np.sqrt(np.maximum(r ** 2 - rho ** 2, 0))  # each hemisphere's centre
        h = centre[~band].mean()
        np.testing.assert_allclose(centre[~band], h, atol=1e-6)
        assert (abs(z[band]) <= h + 1e-4).all() and not flat.any()  # 1e-4: rims within 1e-9 of r
        _share(~band, r / (r + h))
        _share(z > 0, 0.5)
        _round(p)
        return {"r": r, "h": h}
    if name == "torus":  # tube radius r about the unit circle; the outer half has more area
        r = np.hypot(rho - 1, z)
        np.testing.assert_allclose(r, r[0], rtol=1e-12)
        assert not flat.any()
        _share(rho > 1, 0.5 + r[0] / math.pi)
        _share(z > 0, 0.5)
        _round(p)
        return {"r": r[0]}
    if name == "pyramid":  # square base |x|, |y| <= 1 at z = 0; four sides up to the apex at h
        base = abs(z) < 1e-12
        m = np.maximum(abs(x), abs(y))
        h = z[~base] / (1 - m[~base])
        np.testing.assert_allclose(h, h[0], rtol=1e-9)
        assert (m[base] <= 1 + 1e-12).all() and flat.all()
        slant = math.hypot(h[0], 1)
        _share(base, 1 / (1 + slant))
        _round(p[base])  # the square base evenly, not one triangle twice
        for k in range(4):  # each side by the quadrant it faces
            _share(~base & (np.argmax([x, y, -x, -y], 0) == k), slant / (1 + slant) / 4)
        return {"h": h[0]}
    if name == "octahedron":  # |x| + |y| + |z| / s = 1, the eight faces equal
        s = abs(z) / (1 - abs(x) - abs(y))
        np.testing.assert_allclose(s, np.median(s), rtol=1e-6)
        assert flat.all()
        octant = (x > 0) * 4 + (y > 0) * 2 + (z > 0)
        for k in range(8):
            _share(octant == k, 1 / 8)
        return {"s": np.median(s)}
    raise AssertionError(name)


RANGES = {"ellipsoid": {"b": (0.45, 0.6), "c": (0.25, 0.35)},
          "plate": {"b": (0.7, 1.0), "c": (0.08, 0.15)},
          "cylinder": {"r": (0.45, 0.6), "h": (0.8, 1.2)}, "cone": {"r": (0.6, 0.8), "h": (0.9, 1.2)},
          "capsule": {"r": (0.35, 0.45), "h": (0.5, 0.7)}, "torus": {"r": (0.25, 0.4)},
          "pyramid": {"h": (0.9, 1.3)}, "octahedron": {"s": (0.8, 1.3)}}


@pytest.mark.parametrize("name", SHAPES)
def test_each_shape_lies_on_its_surface_spread_by_area_in_its_proportions(name):
    fitted = [_surface(name, *make_shape(name, 200_000 if seed == 0 else 500, np.random.default_rng(seed),
                                         noise=0.0, scale=(1.0, 1.0)))
              for seed in range(30)]
    for key, (lo, hi) in RANGES.get(name, {}).items():
        got = np.array([f[key] for f in fitted])
        assert (got >= lo - 2e-3).all() and (got <= hi + 2e-3).all(), (key, got.min(), got.max())
        assert got.max() - got.min() > (hi - lo) / 2  # the jitter spans its range


def test_make_shape_scales_and_adds_noise():
    clean, part = make_shape("sphere", 4000, np.random.default_rng(1), noise=0.0, scale=(2.0, 2.0))
    np.testing.assert_allclose(np.linalg.norm(clean, axis=1), 2, rtol=1e-12)
    noisy, _ = make_shape("sphere", 4000, np.random.default_rng(1), noise=0.05, scale=(2.0, 2.0))
    d = noisy - clean
    assert abs(d.std() - 0.05) < 0.003 and abs(d.mean()) < 0.003
    sizes = [np.linalg.norm(make_shape("sphere", 10, np.random.default_rng(s))[0], axis=1).mean()
             for s in range(200)]
    assert 0.7 - 0.02 < min(sizes) < 0.75 and 1.35 < max(sizes) < 1.4 + 0.02
    with pytest.raises(ValueError, match="unknown shape 'blob'"):
        make_shape("blob", 10, np.random.default_rng(0))
