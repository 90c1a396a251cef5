"""RigFrontend: the cameras of a rig lifted onto one sphere."""

import math

import numpy as np
import pytest
import torch

from tests.helpers import FIXTURES
from usf_graph import cameras, grids
from usf_graph.frontend import GeometryCache, RigFrontend, SphericalFrontend


def scene(p):
    """A smooth RGB world seen from the rig's centre, as a function of the direction."""
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    return np.stack([0.5 + 0.4 * np.sin(2 * x + y), 0.5 + 0.4 * np.cos(3 * z - y),
                     0.5 + 0.3 * x * z], -1)


def shoot(cam):
    """The image ``cam`` takes of :func:`scene` (0 where it has no ray)."""
    rays, valid = cam.lens_normal_map()
    return np.where(valid[..., None], scene(np.nan_to_num(rays)), 0.0)


@pytest.fixture(scope="module")
def rig():
    cams = {n: c.with_fov(190) for n, c in cameras.load_rig(FIXTURES / "kalibr_rig.yaml").items()}
    return cams, grids.icosahedral(3), GeometryCache(None)


def test_two_opposite_fisheyes_cover_the_sphere_and_agree_where_both_see(rig):
    cams, g, cache = rig
    fe = RigFrontend(cams, g, cache=cache)
    pos = g.pos.numpy()
    assert fe.mask.all()  # two 190-degree lenses back to back see everything
    assert (fe.source[pos[:, 0] > 0] == 0).all() and (fe.source[pos[:, 0] < 0] == 1).all()
    shots = [shoot(c) for c in cams.values()]
    alone = [SphericalFrontend(c, g, cache=cache) for c in cams.values()]
    both = alone[0].mask & alone[1].mask
    assert 20 < int(both.sum()) and np.abs(pos[both.numpy(), 0]).max() < math.sin(math.radians(5)) + 1e-9
    x0, x1 = (a.lift(s) for a, s in zip(alone, shots))
    truth = torch.from_numpy(scene(pos))
    # a point seen by both cameras gets the same value from either side
    assert (x0[both] - x1[both]).abs().max() < 2e-3
    for blend in ("best", "feather"):
        rf = RigFrontend(cams, g, blend=blend, cache=cache)
        img = rf(shots)
        assert img.mask.all() and (img.x - truth).abs().max() < 2e-3
        torch.testing.assert_close(rf.weights.sum(0), torch.ones(len(g), dtype=torch.float64))
    feather = RigFrontend(cams, g, blend="feather", cache=cache)
    assert ((feather.weights > 0).sum(0) == 2).sum() == int(both.sum())  # blended in the overlap
    best = RigFrontend(cams, g, cache=cache)
    np.testing.assert_array_equal(best(shots).x[~both].numpy(),
                                  torch.where(fe.source[~both, None] == 0, x0[~both], x1[~both]).numpy())


def test_rig_inputs_batches_and_errors(rig):
    cams, g, cache = rig
    fe = RigFrontend(cams, g, cache=cache)
    shots = [shoot(c) for c in cams.values()]
    x = fe.lift(shots)
    torch.testing.assert_close(fe.lift({"cam1": shots[1], "cam0": shots[0]}), x)
    xb = fe.lift_batch([np.stack([s, 2 * s]) for s in shots])
    torch.testing.assert_close(xb, torch.stack([x, 2 * x]))
    assert "cam0=kannala-brandt" in repr(fe)
    with pytest.raises(ValueError, match="2 cameras.*1 images"):
        fe.lift(shots[:1])
    with pytest.raises(ValueError, match=r"no image for camera\(s\) \['cam1'\]"):
        fe.lift({"cam0": shots[0]})
    with pytest.raises(ValueError, match="blend"):
        RigFrontend(cams, g, blend="average")
    img = RigFrontend.from_file(FIXTURES / "kalibr_rig.yaml", g, cache=cache)(shots)
    assert img.mask.all() and img.edge_attr.shape[1] == 1


def ball_shots(rig, radius):
    """Each camera's image of :func:`scene` painted on a sphere of ``radius`` about the
    rig's centre, ray cast by trimesh from the camera's own centre; and the cameras
    stitched there."""
    import trimesh

    at = cameras.stitch_at(rig, radius)  # centred between the cameras
    ball = trimesh.creation.icosphere(subdivisions=7, radius=radius)
    shots = []
    for cam in at.values():
        rays, valid = cam.unproject(cam.pixel_grid())
        d = rays[valid] @ cam.rotation.T
        hit, idx, _ = ball.ray.intersects_location(np.broadcast_to(cam.position, d.shape), d,
                                                   multiple_hits=False)
        p = np.full(d.shape, np.nan)
        p[idx] = hit / np.linalg.norm(hit, axis=1, keepdims=True)
        assert np.isfinite(p).all()  # every ray from inside meets the sphere
        # the camera's lens normal map is where its rays meet the sphere, as trimesh found
        np.testing.assert_allclose(cam.lens_normal_map()[0][valid], p, atol=2e-5)
        img = np.zeros((cam.height, cam.width, 3))
        img[valid] = scene(p)
        shots.append(img)
    return at, shots


def test_cameras_apart_line_up_on_a_scene_at_the_stitching_distance():
    """A textured sphere of radius 1 m around the back-to-back fisheyes, 0.1 m apart, ray
    cast by trimesh from each camera's centre: stitched at 1 m the seams close."""
    radius = 1.0
    g = grids.icosahedral(4)
    rig = {n: c.with_fov(190) for n, c in cameras.load_rig(FIXTURES / "kalibr_rig.yaml").items()}
    at, shots = ball_shots(rig, radius)
    truth = torch.from_numpy(scene(g.pos.numpy()))
    stitched = RigFrontend(rig, g, distance=radius, blend="feather")
    assert "distance=1" in repr(stitched)
    img = stitched(shots)
    err = (img.x - truth)[img.mask].abs().max()
    apart = [SphericalFrontend(c, g) for c in at.values()]
    both = apart[0].mask & apart[1].mask
    a, b = (fe.lift(s) for fe, s in zip(apart, shots))
    seam = (a[both] - b[both]).abs().max()
    infinity = RigFrontend(rig, g, blend="feather")  # the baseline ignored
    err_inf = (infinity(shots).x - truth)[img.mask].abs().max()
    assert img.mask.all() and int(both.sum()) > 20  # at 1 m the two fields overlap
    assert err < 3e-4 and seam < 3e-4 and err_inf > 0.03  # ignored, the baseline shifts up to 2.9 deg


def test_choose_distance_finds_the_scene_sphere():
    """The seams agree best at the radius of the sphere the cameras see, among candidates."""
    from usf_graph.frontend import choose_distance

    rig = {n: c.with_fov(190) for n, c in cameras.load_rig(FIXTURES / "kalibr_rig.yaml").items()}
    g = grids.icosahedral(4)
    for radius in (0.6, 1.5):
        _, shots = ball_shots(rig, radius)
        best, err = choose_distance(rig, g, shots, candidates=(0.6, 0.9, 1.5, 3.0, None))
        assert best == radius and set(err) == {0.6, 0.9, 1.5, 3.0, None}
        assert err[best] < 0.2 * min(e for d, e in err.items() if d != best)
    # candidates within the rig are left out; a lone camera has no seam
    _, err = choose_distance(rig, g, shots, candidates=(0.01, 1.5))
    assert set(err) == {1.5}
    with pytest.raises(ValueError, match="no two cameras of the rig see one grid point at any"):
        choose_distance(rig, g, shots, candidates=(0.52,))  # the fields leave a gap that near
    with pytest.raises(ValueError, match="every candidate distance lies within the rig"):
        choose_distance(rig, g, shots, candidates=(0.01, 0.05))
    with pytest.raises(ValueError, match="the rig needs two"):
        choose_distance({"cam0": rig["cam0"]}, g, shots[:1])
    with pytest.raises(ValueError, match="2 cameras .* but 1 images"):
        choose_distance(rig, g, shots[:1])


def test_render_rig_stitches_the_cameras_into_one_panorama():
    """Two back-to-back fisheyes 0.1 m apart photograph a painted sphere of radius 1 m (ray
    cast by trimesh): stitched at 1 m and re-imaged as a panorama they give the painting
    seen from the centre, with either blend; ignoring the baseline does not. A labelled
    panorama comes back reading as it did (no mirror)."""
    from usf_graph.frontend import render, render_rig
    from usf_graph.viz import labelled_panorama

    rig = {n: c.with_fov(190) for n, c in cameras.load_rig(FIXTURES / "kalibr_rig.yaml").items()}
    at, shots = ball_shots(rig, 1.0)
    pano = cameras.Equirectangular(256, 128)
    truth = scene(pano.lens_normal_map()[0])
    for blend in ("best", "feather"):
        out = render_rig(shots, at, pano, blend=blend)
        assert out.shape == (128, 256, 3) and (out.sum(-1) > 0).all()  # every direction seen
        assert np.abs(out - truth).mean() < 2e-3 and np.abs(out - truth).max() < 0.05
    apart = render_rig(shots, {n: c.with_distance(None) for n, c in at.items()}, pano)
    assert np.abs(apart - truth).max() > 0.03  # the baseline ignored: the seams shift
    text = (255 * labelled_panorama(512, 256)).round().astype(np.uint8)
    big = cameras.Equirectangular(512, 256)
    views = {n: render(text, big, c) for n, c in rig.items()}
    back = render_rig(dict(reversed(views.items())), rig, big)  # by name, in any order
    assert back.dtype == np.uint8 and np.abs(back.astype(int) - text).mean() < 8
    deep = render_rig({n: v.astype(np.uint16) * 257 for n, v in views.items()}, rig, big)
    assert deep.dtype == np.uint16 and np.abs(deep.astype(int) - 257 * back.astype(int)).max() <= 257
    one = render_rig([views["cam0"]], [rig["cam0"]], big)  # one camera: render back
    exact = render(views["cam0"].astype(float), rig["cam0"], big).round()  # float64: the exact table
    assert one.dtype == np.uint8 and np.abs(one - exact).max() <= 1  # cv2.remap's 1/32 pixel
    with pytest.raises(ValueError, match=r"2 cameras \(cam0, cam1\) but 1 images"):
        render_rig([views["cam0"]], rig, big)
    with pytest.raises(ValueError, match="blend must be one of"):
        render_rig(list(views.values()), rig, big, blend="max")


def test_blend_weights_against_the_angles_to_each_optical_axis(rig):
    """``feather`` weighs each camera by the angle left to its field's edge, with the axis
    found independently (the ray of its principal point); a direction seen by none has no
    weight and no best camera; one seen only past every field's edge (as a caller's mask
    may say) goes wholly to the nearest axis, even at a tie."""
    from usf_graph.frontend.rig import blend_weights

    def axes(cams):  # the camera's frame turned into the rig's
        return np.stack([c.unproject(np.array([[c.params()["cx"], c.params()["cy"]]]))[0][0]
                         @ c.rotation.T for c in cams])

    cams = [c.with_fov(200) for c in rig[0].values()]
    pos = grids.fibonacci(400).pos.numpy()
    seen = np.stack([c.sees(pos)[1] for c in cams])
    seen[:, 5] = False
    ang = np.arccos(np.clip(pos @ axes(cams).T, -1, 1)).T  # [K, M]
    edge = np.array([[c.max_incidence] for c in cams])
    assert np.allclose(edge, math.radians(100), atol=1e-4)
    share = np.where(seen, np.maximum(edge - ang, 0), 0)
    w, best = blend_weights(cams, pos, seen, "feather")
    assert (share > 0).all(0).sum() > 20  # blended somewhere
    ok = share.sum(0) > 0
    assert ok.sum() == 399
    np.testing.assert_allclose(w[:, ok], share[:, ok] / share[:, ok].sum(0), rtol=1e-9, atol=1e-12)
    assert best[5] == -1 and (w[:, 5] == 0).all()
    np.testing.assert_array_equal(best[ok], np.where(ang[0] <= ang[1], 0, 1)[ok])
    wb, _ = blend_weights(cams, pos, seen, "best")
    np.testing.assert_array_equal(wb, (np.arange(2)[:, None] == best[None]) & seen)
    narrow = [c.with_fov(170) for c in rig[0].values()]  # edges at 85 degrees
    past = np.array([[0.0, 1.0, 0.0], [0.01, 0.0, 1.0]])  # a tie, then nearer cam0
    past /= np.linalg.norm(past, axis=1, keepdims=True)
    assert (np.degrees(np.arccos(np.abs(past @ axes(narrow).T))) > 85).all()
    w, best = blend_weights(narrow, past, np.ones((2, 2), bool), "feather")
    np.testing.assert_array_equal(w, [[1.0, 1.0], [0.0, 0.0]])
    assert best.tolist() == [0, 0]


def test_rig_reimager_takes_grey_images_and_refuses_mixed_ones(rig):
    from usf_graph.frontend import render_rig

    cams, _, _ = rig
    shots = [shoot(c).astype(np.float32) for c in cams.values()]
    pano = cameras.Equirectangular(64, 32)
    for blend in ("best", "feather"):
        colour = render_rig(shots, cams, pano, blend=blend)
        grey = render_rig([s[..., 1] for s in shots], cams, pano, blend=blend)
        assert grey.shape == (32, 64) and np.array_equal(grey, colour[..., 1])
    with pytest.raises(ValueError, match=r"differ in channels or type: \[\(3, 'float32'\), \(2, 'float32'\)\]"):
        render_rig([shots[0], shots[1][..., :2]], cams, pano)
    with pytest.raises(ValueError, match="at least one camera"):
        RigFrontend([], grids.icosahedral(1))
