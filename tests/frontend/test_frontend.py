import math
import subprocess
import sys
import warnings

import numpy as np
import pytest
import torch
from torch_geometric.loader import DataLoader

from usf_graph import SphericalFrontend, cameras, grids
from usf_graph.frontend import GeometryCache, render
from usf_graph.frontend.interpolation import valid_entries
from usf_graph.geometry import to_latlon


def smooth(p):
    lat, lon = to_latlon(p)
    return np.cos(lat) ** 2 * np.cos(2 * lon) + 0.5 * np.sin(lat)


def equirect_image(W):
    cam = cameras.Equirectangular(W, W // 2)
    lnm, _ = cam.lens_normal_map()
    return cam, smooth(lnm)


def test_bilinear_converges_at_second_order():
    g = grids.fibonacci(2000)
    errs = []
    for W in (32, 64, 128, 256):
        cam, img = equirect_image(W)
        fe = SphericalFrontend(cam, g, cache=GeometryCache(None))
        x = fe.lift(img)[:, 0].numpy()
        errs.append(np.abs(x - smooth(g.pos.numpy())).max())
    slope = -np.polyfit(np.log([32, 64, 128, 256]), np.log(errs), 1)[0]
    assert 1.8 < slope < 2.3, (errs, slope)


@pytest.mark.parametrize("cam, expect", [
    (cameras.Pinhole(200, 200, 199.5, 149.5, 400, 300), None),
    (cameras.Fisheye(100, 255.5, 255.5, 512, 512, fov_deg=180), 2 * math.pi),
    (cameras.KannalaBrandt(120, 120, 299.5, 299.5, 600, 600, k=(0.01, 0, 0, 0), fov_deg=200), None),
    (cameras.Equirectangular(128, 64), 4 * math.pi),
])
def test_field_of_view_coverage_matches_solid_angle(cam, expect):
    g = grids.fibonacci(20000)
    fe = SphericalFrontend(cam, g, cache=GeometryCache(None))
    frac = float(fe.mask.double().mean())
    om = cam.solid_angle() if expect is None else expect
    if isinstance(cam, cameras.KannalaBrandt):  # analytic: a cap of 100 degrees
        om = 2 * math.pi * (1 - math.cos(math.radians(100)))
    if isinstance(cam, cameras.Pinhole):  # analytic: a rectangular pyramid
        a, b = 200 / 200, 150 / 200
        om = 4 * math.asin(a * b / math.sqrt((1 + a * a) * (1 + b * b)))
    assert frac == pytest.approx(om / (4 * math.pi), abs=0.01)


def test_cache_hit_corrupt_file_and_counts(tmp_path):
    cam, img = equirect_image(64)
    g = grids.icosahedral(3)
    c = GeometryCache(tmp_path)
    fe = SphericalFrontend(cam, g, cache=c)
    assert c.builds == 1  # the lift table; the graph waits until it is used
    fe.lift(img)
    assert c.builds == 1
    ei = fe(img).edge_index
    assert c.builds == 2 and ei is fe.edge_index
    fe2 = SphericalFrontend(cam, g, cache=c)
    assert torch.equal(fe2.lift(img), fe.lift(img)) and torch.equal(fe2.edge_weight, fe.edge_weight)
    assert c.builds == 2
    c2 = GeometryCache(tmp_path)  # a new process: served from disk
    fe3 = SphericalFrontend(cam, g, cache=c2)
    assert c2.builds == 0 and torch.equal(fe3.lift(img), fe.lift(img))
    for f in tmp_path.glob("lift-*.npz"):
        f.write_bytes(b"garbage")
    c3 = GeometryCache(tmp_path)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        fe4 = SphericalFrontend(cam, g, cache=c3)
    assert c3.builds == 1 and any("corrupt" in str(x.message) for x in w)
    assert torch.equal(fe4.lift(img), fe.lift(img))


def test_two_processes_fill_one_key(tmp_path):
    code = ("import sys; from usf_graph import SphericalFrontend, cameras, grids; "
            "from usf_graph.frontend import GeometryCache; "
            "fe = SphericalFrontend(cameras.Equirectangular(256, 128), grids.icosahedral(4), "
            "interpolation='area', cache=GeometryCache(sys.argv[1])); print(int(fe.mask.sum()))")
    ps = [subprocess.Popen([sys.executable, "-c", code, str(tmp_path)], stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE) for _ in range(2)]
    outs = [p.communicate(timeout=300) for p in ps]
    assert all(p.returncode == 0 for p in ps), outs
    assert [o[0].strip() for o in outs] == [b"2562", b"2562"]
    assert not list(tmp_path.glob("*.tmp"))


@pytest.mark.parametrize("sigma", [None, 0.08])
def test_rbf_lift_is_the_gaussian_mean_of_the_pixels_within_three_sigma(sigma):
    """Each visible point: sum_j g_j x_j / sum_j g_j over the pixels j whose rays lie
    within 3 sigma (geodesic) of it, g_j = exp(-d_j^2 / 2 sigma^2), sigma by default half
    the grid's spacing; brute force over every pixel ray."""
    cam = cameras.Fisheye(30, 31.5, 31.5, 64, 64, fov_deg=180)
    g = grids.icosahedral(3)
    img = np.random.default_rng(0).random((64, 64))
    fe = SphericalFrontend(cam, g, interpolation="rbf", rbf_sigma=sigma, cache=GeometryCache(None))
    got = fe.lift(img).numpy()[:, 0]  # [N, 1]: one channel
    s = 0.5 * g.spacing if sigma is None else sigma
    rays, valid = cam.lens_normal_map()
    rays, vals = rays[valid], img[valid]
    d = np.arccos(np.clip(g.pos.numpy() @ rays.T, -1, 1))
    w = np.where(d <= 3 * s, np.exp(-0.5 * (d / s) ** 2), 0.0)
    seen = fe.mask.numpy()
    assert seen.sum() > 100
    want = w @ vals / np.maximum(w.sum(1), 1e-300)
    np.testing.assert_allclose(got[seen], want[seen], rtol=0, atol=1e-9)


def test_interpolations_fov_mask_and_errors():
    cam = cameras.Fisheye(40, 63.5, 63.5, 128, 128, fov_deg=180)
    g = grids.icosahedral(3)
    img = np.full((128, 128), 0.7)
    for method in ("bilinear", "nearest", "area", "rbf"):
        fe = SphericalFrontend(cam, g, interpolation=method, cache=GeometryCache(None))
        x = fe.lift(img)
        assert torch.allclose(x[fe.mask], torch.full_like(x[fe.mask], 0.7))  # rows sum to 1
        assert (x[~fe.mask] == 0).all()
        assert 0.4 < fe.mask.double().mean() < 0.6
    vign = np.zeros((128, 128), bool)
    vign[:, :64] = True
    fe = SphericalFrontend(cam, g, image_mask=vign, cache=GeometryCache(None))
    assert 0.15 < fe.mask.double().mean() < 0.35
    with pytest.raises(ValueError, match="expects"):
        fe(np.zeros((100, 128)))
    with pytest.raises(ValueError, match="no channels"):
        fe(np.zeros((128, 128, 0), np.uint8))
    with pytest.raises(ValueError, match=r"valid is \(64, 128\), the camera's image \(128, 128\)"):
        valid_entries(cam, np.zeros((3, 4), np.int64), np.ones((3, 4)), valid=vign[::2])
    with pytest.raises(ValueError, match="unknown interpolation 'bicubic'"):
        SphericalFrontend(cam, g, interpolation="bicubic", cache=GeometryCache(None))
    for r in (-1.0, 0.0, float("nan"), 4.0):  # when built, not when the graph is first used
        with pytest.raises(ValueError, match=r"radius must be in \(0, pi\] radians"):
            SphericalFrontend(cam, g, radius=r, cache=GeometryCache(None))
    bad = img.copy()
    bad[40:90, 20:60] = np.nan  # pixels the masked camera still sees
    with pytest.raises(ValueError, match="NaN"):
        fe(bad)
    away = cam.with_rotation(np.array([[0, 0, -1.0], [1, 0, 0], [0, -1, 0]]))
    with pytest.raises(ValueError, match="empty field of view"):
        SphericalFrontend(cameras.Pinhole(10, 10, 1.5, 1.5, 4, 4, rotation=away.rotation),
                          grids.icosahedral(0), cache=GeometryCache(None))


def test_area_interpolation_averages_each_cell_and_does_not_alias():
    # a pixel-level checkerboard panorama onto a grid ~20x coarser than the pixels
    cam = cameras.Equirectangular(512, 256)
    board = (np.add.outer(np.arange(256), np.arange(512)) % 2).astype(np.float64)
    g = grids.icosahedral(3)  # 642 points, spacing ~8 deg vs 0.7 deg pixels
    area = SphericalFrontend(cam, g, interpolation="area", cache=GeometryCache(None)).lift(board)
    near = SphericalFrontend(cam, g, interpolation="nearest", cache=GeometryCache(None)).lift(board)
    assert (area - 0.5).abs().max() < 0.03  # each cell averages ~100 pixels or more
    assert set(near.unique().tolist()) == {0.0, 1.0}  # point sampling aliases
    # a cell's value is the solid-angle weighted mean of the pixels nearest to its point
    lnm, _ = cam.lens_normal_map()
    owner = np.argmax(lnm.reshape(-1, 3) @ g.pos.numpy().T, axis=1)
    w = cam.pixel_solid_angles().ravel()
    ramp = np.linspace(0, 1, 256 * 512).reshape(256, 512)
    ref = np.bincount(owner, w * ramp.ravel(), len(g)) / np.bincount(owner, w, len(g))
    x = SphericalFrontend(cam, g, interpolation="area", cache=GeometryCache(None)).lift(ramp)
    np.testing.assert_allclose(x[:, 0].numpy(), ref, rtol=1e-9)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_non_finite_pixels_raise_only_where_the_camera_sees(dtype):
    cam = cameras.Fisheye(40, 63.5, 63.5, 128, 128, fov_deg=180)
    vign = np.zeros((128, 128), bool)
    vign[:, :64] = True
    fe = SphericalFrontend(cam, grids.icosahedral(3), image_mask=vign, cache=GeometryCache(None))
    for bad in (np.inf, -np.inf, np.nan):
        img = np.full((128, 128), 0.5, dtype)
        img[60:70, 20:30] = bad  # seen
        with pytest.raises(ValueError, match="NaN or inf.*--image-mask"):
            fe.lift(img)
        img[:] = 0.5
        img[:, 100:] = bad  # hidden by the image mask: allowed
        assert torch.isfinite(fe.lift(img)).all()
    img = np.full((128, 128), 0.5, dtype)
    img[60:70, 20:25], img[60:70, 25:30] = np.inf, -np.inf  # sum is NaN, not inf
    with pytest.raises(ValueError, match="NaN or inf.*--image-mask"):
        fe.lift(img)
    huge = np.full((128, 128), 3e38, dtype)  # finite, however large
    assert torch.isfinite(fe.lift(huge)).all()
    assert torch.isfinite(fe.lift_batch(huge[None, ..., None])).all()


def test_remap_fast_path_equals_gather_and_batches():
    cam, img = equirect_image(128)
    g = grids.icosahedral(4)
    fe = SphericalFrontend(cam, g, cache=GeometryCache(None))
    exact = fe.lift(img)  # float64: exact gather
    fast = fe.lift(img.astype(np.float32))  # cv2.remap, weights quantized to 1/32 pixel
    assert (fast - exact.float()).abs().max() < 0.02
    b = fe.lift_batch(np.stack([img, 2 * img])[..., None])
    torch.testing.assert_close(b[1], 2 * exact)


@pytest.mark.parametrize("interpolation", ["bilinear", "nearest"])
def test_remap_fast_path_leaves_out_pixels_without_a_ray_and_masked_ones(interpolation):
    """A fisheye whose image circle leaves the corners without rays, and an image mask:
    the table leaves those pixels out and renormalizes; the cv2.remap path (numpy uint8 and
    float32 images) must agree, whatever values those pixels hold."""
    fish = cameras.KannalaBrandt(20.0, 20.0, 31.5, 31.5, 64, 64, k=(0.0, 0.0, 0.0, 0.0)).with_fov(190)
    assert not fish.unproject(fish.pixel_grid())[1].all()
    body = np.ones((64, 64), bool)
    body[40:, 20:44] = False  # the robot's body
    img = np.random.default_rng(0).integers(0, 256, (64, 64, 3)).astype(np.uint8)
    for mask in (None, body):
        fe = SphericalFrontend(fish, grids.icosahedral(4), interpolation=interpolation,
                               image_mask=mask, cache=GeometryCache(None))
        exact = fe.lift(torch.as_tensor(img).double())  # the table, float64
        for arr in (img, img.astype(np.float32)):
            fast = fe.lift(arr)
            assert fast.dtype == torch.float32  # as from any image, whatever its type
            assert (fast - exact.float()).abs().max() < (0.501 if arr.dtype == np.uint8 else 1e-3)  # uint8: rounded
        if mask is not None:  # what the mask hides does not matter
            other = img.copy()
            other[~body] = 255
            assert torch.equal(fe.lift(other), fe.lift(img))


@pytest.mark.parametrize("interpolation", ["bilinear", "nearest"])
def test_remap_fast_path_on_a_masked_panorama_keeps_unseen_points_zero(interpolation):
    """A panorama wraps around, so the remap path's unseen points read wrapped pixels; where
    the image mask hides NaN or inf there, they must still come out 0, as on the table path,
    and the seen points must not change."""
    pano = cameras.Equirectangular(128, 64)
    mask = np.ones((64, 128), bool)
    mask[40:] = False  # the lower part: the robot's body
    rng = np.random.default_rng(1)
    img = rng.random((64, 128, 3)).astype(np.float32)
    bad = img.copy()
    bad[~mask] = np.where(rng.random(((~mask).sum(), 3)) < 0.5, np.nan, np.inf)
    fe = SphericalFrontend(pano, grids.icosahedral(3), interpolation=interpolation,
                           image_mask=mask, cache=GeometryCache(None))
    assert 0.3 < fe.mask.float().mean() < 0.9
    fast, table = fe.lift(bad), fe.lift(torch.from_numpy(bad).double())
    assert torch.isfinite(fast).all() and (fast[~fe.mask] == 0).all()
    assert (fast - table.float()).abs().max() < 1e-3
    assert torch.equal(fast, fe.lift(img))


@pytest.mark.parametrize("interpolation", ["bilinear", "nearest"])
def test_render_leaves_out_source_pixels_without_a_ray(interpolation):
    """Re-imaging a fisheye as a panorama reads what the fisheye sees only: whatever its
    corners hold (past the image circle) never reaches the panorama, and a constant
    image stays constant up to the field's edge."""
    fish = cameras.KannalaBrandt(20.0, 20.0, 31.5, 31.5, 64, 64, k=(0.0, 0.0, 0.0, 0.0)).with_fov(190)
    valid = fish.unproject(fish.pixel_grid())[1]
    img = np.where(valid, 0.5, 1e6)[..., None]
    img[~valid & (np.arange(64) % 2 == 0)[None, :]] = np.nan  # past the image circle
    pano = cameras.Equirectangular(128, 64)
    out = render(img, fish, pano, interpolation=interpolation)[..., 0]
    seen = out != 0
    assert seen.mean() > 0.4
    np.testing.assert_allclose(out[seen], 0.5, atol=1e-12)
    left = (np.arange(64) < 32)[None, :].repeat(64, 0)  # an image mask: the left half
    out = render(np.where(left & valid, 0.5, 1e6)[..., None], fish.with_image_mask(left), pano,
                 interpolation=interpolation)[..., 0]
    np.testing.assert_allclose(out[out != 0], 0.5, atol=1e-12)
    assert 0.1 < (out != 0).mean() < seen.mean()


def test_render_with_the_source_valid_pixels_given_matches_it_computing_them():
    """``source_valid`` (a caller's valid_pixels, reused across targets) changes nothing:
    the same image as without it, and the pixels a given map leaves out are left out. A map
    of another shape is refused."""
    from usf_graph.frontend.interpolation import valid_pixels

    fish = cameras.KannalaBrandt(20.0, 20.0, 31.5, 31.5, 64, 64, k=(0.0, 0.0, 0.0, 0.0)).with_fov(190)
    img = np.random.default_rng(0).random((64, 64, 2))
    left = (np.arange(64) < 32)[None, :].repeat(64, 0)
    for dst in (cameras.Equirectangular(96, 48), cameras.Pinhole(20.0, 20.0, 19.5, 19.5, 40, 40)):
        for interpolation in ("bilinear", "nearest"):
            np.testing.assert_array_equal(
                render(img, fish, dst, interpolation, source_valid=valid_pixels(fish)),
                render(img, fish, dst, interpolation))
            # the pixels left out never blend in (1e6 there would show)
            out = render(np.where(left[..., None], img, 1e6), fish, dst, interpolation,
                         source_valid=valid_pixels(fish) & left)
            assert 0 < (out != 0).mean() and out.max() <= 1.0
    with pytest.raises(ValueError, match="the camera's image"):
        render(img, fish, dst, source_valid=np.ones((32, 64), bool))


def test_data_loader_offsets_and_to_image_and_render():
    cam, img = equirect_image(64)
    g = grids.icosahedral(2)
    fe = SphericalFrontend(cam, g, cache=GeometryCache(None))
    data = [fe(img), fe(2 * img)]
    batch = next(iter(DataLoader(data, batch_size=2)))
    E, N = data[0].edge_index.shape[1], len(g)
    assert batch.x.shape == (2 * N, 1) and batch.mask.shape == (2 * N,)
    assert torch.equal(batch.edge_index[:, E:], data[1].edge_index + N)
    assert batch.lat.shape == (2 * N,)
    # lat/lon follow the design's convention: p = (cos lat cos lon, cos lat sin lon, sin lat)
    lat, lon = batch.lat, batch.lon
    torch.testing.assert_close(torch.stack([lat.cos() * lon.cos(), lat.cos() * lon.sin(),
                                            lat.sin()], -1), batch.pos, rtol=0, atol=1e-6)
    torch.testing.assert_close(batch.x[N:], 2 * batch.x[:N])
    back = fe.to_image(fe.lift(img)[:, 0].numpy())
    assert np.abs(back - img).mean() < 0.05
    labels = fe.to_image(torch.arange(N), mode="nearest")
    assert labels.dtype == torch.int64 and set(labels.unique().tolist()) <= set(range(N))
    nan = torch.zeros(N)
    nan[3] = float("nan")
    with pytest.raises(ValueError, match="NaN or inf at 1 grid points the camera sees"):
        fe.to_image(nan)
    two = torch.zeros(N, 3)
    two[[3, 9], 1] = float("inf")  # counted by point, not by channel
    with pytest.raises(ValueError, match="NaN or inf at 2 grid points"):
        fe.to_image(two)
    pin = SphericalFrontend(cameras.Pinhole(20, 20, 15.5, 11.5, 32, 24), g, cache=GeometryCache(None))
    hidden = torch.zeros(N)
    hidden[~pin.mask] = float("nan")  # never read: the pinhole does not see them
    assert torch.isfinite(pin.to_image(hidden)).all()
    fish = cameras.Fisheye(40, 63.5, 63.5, 128, 128, fov_deg=190)
    out = render(img, cam, fish)
    lnm, valid = fish.lens_normal_map()
    assert np.abs(out[valid] - smooth(lnm[valid])).max() < 0.05


def test_tables_of_an_older_geometry_convention_are_not_read(tmp_path, monkeypatch):
    import usf_graph.frontend.cache as cache_module

    cam, img = equirect_image(64)
    g = grids.icosahedral(2)
    SphericalFrontend(cam, g, cache=GeometryCache(tmp_path))
    monkeypatch.setattr(cache_module, "GEOMETRY_VERSION", cache_module.GEOMETRY_VERSION + 1)
    c = GeometryCache(tmp_path)  # a newer convention: the old file is another key
    SphericalFrontend(cam, g, cache=c)
    assert c.builds == 1 and len(list(tmp_path.glob("lift-*.npz"))) == 2


def test_to_labels_nearest_and_soft_against_their_definitions():
    """``nearest`` is the label image of the points' argmax; ``soft`` the argmax of the
    probabilities blended as ``to_image``'s bilinear (computed whole here, in chunks
    there); on a pinhole much finer than the grid, soft labels follow a boundary between
    two classes closer than nearest ones."""
    g = grids.icosahedral(3)
    fish = SphericalFrontend(cameras.Fisheye(30, 47.5, 47.5, 96, 96, fov_deg=190), g,
                             cache=GeometryCache(None))
    gen = torch.Generator().manual_seed(0)
    probs = torch.rand(len(g), 5, generator=gen, dtype=torch.float64).softmax(-1)
    probs[~fish.mask] = float("nan")  # hidden points are never read
    ref = fish.to_image(probs.argmax(-1), mode="nearest")
    assert torch.equal(fish.to_labels(probs), ref)
    blended = fish.to_image(torch.nan_to_num(probs), mode="bilinear").argmax(-1)
    soft = fish.to_labels(probs, "soft", chunk=1000)  # 9216 pixels: a partial last chunk
    assert soft.shape == (96, 96) and torch.equal(soft, blended)
    assert (soft != ref).any()  # not the nearest labels under another name
    for bad, match in ((lambda: fish.to_labels(probs, "bilinear"), "nearest' or 'soft"),
                       (lambda: fish.to_labels(probs[:-1], "soft"), r"\[642, C\]"),
                       (lambda: fish.to_labels(torch.full_like(probs, float("nan")), "soft"),
                        "NaN")):
        with pytest.raises(ValueError, match=match):
            bad()
    # two classes split by a tilted great circle, seen by a pinhole 10x finer than the grid
    pin = SphericalFrontend(cameras.Pinhole(120, 120, 127.5, 127.5, 256, 256), g,
                            cache=GeometryCache(None))
    n = torch.nn.functional.normalize(torch.tensor([0.3, 1.0, 0.4], dtype=torch.float64), dim=0)
    side = g.pos.double() @ n
    two = torch.stack([torch.sigmoid(-8 * side), torch.sigmoid(8 * side)], -1)
    rays, valid = pin.camera.lens_normal_map()
    truth = torch.as_tensor(rays.reshape(-1, 3) @ n.numpy() > 0).reshape(256, 256).long()
    wrong = {m: int((pin.to_labels(two, m) != truth)[torch.as_tensor(valid)].sum())
             for m in ("nearest", "soft")}
    assert wrong["soft"] < 0.5 * wrong["nearest"], wrong


@pytest.mark.parametrize("grid", [grids.icosahedral(4), grids.healpix(8), grids.fibonacci(2000)],
                         ids=str)
def test_default_radius_links_each_point_to_its_nearest_ring(grid):
    """About 1.6 spacings: each point, itself included, has 6 to 11 ends of edges, about 7 to
    8 on average (a ring of 6 neighbours and a few of the next), on every kind of grid."""
    fe = SphericalFrontend(cameras.Equirectangular(32, 16), grid, cache=GeometryCache(None))
    assert fe.radius == pytest.approx(1.6 * grid.spacing)
    degree = torch.bincount(fe.edge_index[1], minlength=len(grid))
    assert degree.min() >= 6 and degree.max() <= 11 and 6.5 < degree.double().mean() < 8.5


def test_render_tables_blend_the_nearest_visible_points_by_inverse_squared_chord():
    """Against a brute-force search over the visible points: ``nearest`` gives each pixel
    with a ray its nearest one, ``bilinear`` its three nearest weighted by 1 / d^2 (d the
    chord), pixels without a ray nothing."""
    fish = cameras.KannalaBrandt(9.0, 9.0, 11.5, 11.5, 24, 24, k=(0.0, 0.0, 0.0, 0.0)).with_fov(190)
    g = grids.fibonacci(500)
    fe = SphericalFrontend(fish, g, cache=GeometryCache(None))
    rays, valid = fish.lens_normal_map()
    rays, valid = rays.reshape(-1, 3), valid.ravel()
    assert 0 < valid.sum() < len(valid)
    vis = np.flatnonzero(fe.mask.numpy())
    d = np.linalg.norm(rays[valid, None] - g.pos.numpy()[vis][None], axis=-1)
    order = np.argsort(d, 1)[:, :3]
    near = np.take_along_axis(d, order, 1)
    w = near ** -2.0 / (near ** -2.0).sum(1, keepdims=True)
    for mode, k in (("nearest", 1), ("bilinear", 3)):
        crow, col, val = (t.numpy() for t in fe.render_table(mode))
        np.testing.assert_array_equal(crow, np.arange(0, k * len(valid) + 1, k))
        col, val = col.reshape(-1, k), val.reshape(-1, k)
        assert (val[~valid] == 0).all()
        np.testing.assert_array_equal(col[valid], vis[order[:, :k]])
        np.testing.assert_allclose(val[valid], w if k == 3 else 1.0, rtol=1e-12, atol=0)


def test_the_frontend_refuses_arguments_it_cannot_use():
    cam, g = cameras.Equirectangular(32, 16), grids.icosahedral(2)
    with pytest.raises(ValueError, match=r"image_mask must have shape \(16, 32\)"):
        SphericalFrontend(cam, g, image_mask=np.ones((32, 16), bool), cache=GeometryCache(None))
    fe = SphericalFrontend(cam, g, cache=GeometryCache(None))
    for call in (lambda: fe.to_image(torch.zeros(len(g)), mode="linear"),
                 lambda: fe.render_table("linear")):
        with pytest.raises(ValueError, match="mode must be 'bilinear' or 'nearest', got 'linear'"):
            call()
    with pytest.raises(ValueError, match=f"values have {len(g) - 1} points, the grid has {len(g)}"):
        fe.to_image(np.zeros(len(g) - 1))


def test_lifting_half_precision_images_checks_them_in_torch():
    """bfloat16 and float16 (numpy has no bfloat16): lifted on the table in their own type,
    and NaN refused where the camera sees."""
    cam = cameras.Equirectangular(32, 16)
    fe = SphericalFrontend(cam, grids.icosahedral(2), cache=GeometryCache(None))
    img = torch.rand(2, 16, 32, 3, generator=torch.Generator().manual_seed(0))
    for dtype in (torch.bfloat16, torch.float16):
        x = fe.lift_batch(img.to(dtype))
        assert x.dtype == dtype
        torch.testing.assert_close(x.double(), fe.lift_batch(img.double()), atol=2e-2, rtol=0)
        bad = img.to(dtype).clone()
        bad[1, 5, 7] = float("nan")
        with pytest.raises(ValueError, match="NaN or inf in pixels the camera sees"):
            fe.lift_batch(bad)
