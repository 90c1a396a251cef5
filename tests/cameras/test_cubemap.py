"""Cube maps: py360convert's faces, order and layouts; each face the pinhole it is; points
sampled on their own face; the whole sphere once."""

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from usf_graph import cameras, grids
from usf_graph.cameras import Cubemap, Equirectangular, cube_faces
from usf_graph.cameras.cubemap import FACES, LAYOUTS
from usf_graph.frontend import SphericalFrontend, render
from usf_graph.viz import labelled_panorama


def _smooth_panorama(w: int = 1024) -> np.ndarray:
    """The labelled test panorama, blurred: a smooth picture that still tells faces apart."""
    return cv2.GaussianBlur((255 * labelled_panorama(w, w // 2)).astype(np.float64), (0, 0), 4)


@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_faces_order_and_layout_are_py360converts(layout):
    """The panorama re-imaged into our cube map and py360convert's e2c agree face by face
    (its faces' pixels sit edge to edge, ours at half-pixel offsets: a 1/128 scale apart),
    and each face is far from every other face and from its own mirror images."""
    py360convert = pytest.importorskip("py360convert")
    img = _smooth_panorama()
    cube = Cubemap(128, layout)
    ours = render(img, Equirectangular(1024, 512), cube)
    theirs = py360convert.e2c(img, face_w=128, mode="bilinear", cube_format=layout)
    assert ours.shape == theirs.shape == (cube.height, cube.width, 3)
    cells, _ = LAYOUTS[layout]

    def face(a, k):
        col, row = cells[k]
        return a[row * 128:(row + 1) * 128, col * 128:(col + 1) * 128]

    for k in range(6):
        same = np.abs(face(ours, k) - face(theirs, k)).mean()
        others = [np.abs(face(ours, k) - face(theirs, j)).mean() for j in range(6) if j != k]
        flips = [np.abs(face(ours, k) - f).mean() for f in (face(theirs, k)[::-1], face(theirs, k)[:, ::-1])]
        assert same < 2.5 and min(others + flips) > 10 * same, (FACES[k], same, others, flips)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from(list(LAYOUTS)))
def test_each_face_is_its_pinhole_and_rays_come_back(seed, layout):
    """A ray lands on the face it points most towards, where that face's pinhole puts it
    (plus the face's cell); unprojecting gives the ray back."""
    rng = np.random.default_rng(seed)
    size = int(rng.integers(4, 300))
    cube, faces = Cubemap(size, layout), cube_faces(size)
    rays = rng.normal(size=(500, 3))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    uv, ok = cube.project(rays)
    assert ok.all()
    for k, name in enumerate(FACES):
        R = faces[name].rotation
        on = (rays @ R)[:, 2] >= np.max(np.stack([(rays @ faces[n].rotation)[:, 2] for n in FACES]), 0)
        fuv, fok = faces[name].sees(rays[on])
        assert fok.all()
        col, row = LAYOUTS[layout][0][k]
        np.testing.assert_allclose(uv[on], fuv + [col * size, row * size], atol=1e-9)
    back, ok = cube.unproject(uv)
    assert ok.all()
    np.testing.assert_allclose(back, rays, atol=1e-12)


def test_the_whole_sphere_once_and_empty_cells_without_rays():
    for layout in LAYOUTS:
        cube = Cubemap(32, layout)
        assert math.isclose(cube.solid_angle(), 4 * math.pi, rel_tol=1e-9)
        _, valid = cube.lens_normal_map()
        assert valid.sum() == 6 * 32 * 32  # the dice's six empty cells: no rays
    assert (Cubemap(32, "dice").pixel_solid_angles()[:32, :32] == 0).all()


def test_points_are_sampled_on_their_own_face():
    """Six faces of six colours, lifted onto a fine grid (the cv2.remap fast path and the
    exact table): every point has exactly its face's colour, also within half a pixel of a
    face's edge, where the next cell of the layout is another face."""
    for layout in LAYOUTS:
        cube = Cubemap(16, layout)
        colours = np.arange(1, 7, dtype=np.float32) * 40
        img = np.zeros((cube.height, cube.width), np.float32)
        for (col, row), c in zip(LAYOUTS[layout][0], colours):
            img[row * 16:(row + 1) * 16, col * 16:(col + 1) * 16] = c
        g = grids.healpix(64)
        z = np.stack([(g.pos.double().numpy() @ cube_faces(16)[n].rotation)[:, 2] for n in FACES])
        face, top = np.argmax(z, 0), np.sort(z, 0)
        clear = top[-1] - top[-2] > 1e-6  # not on an edge between two faces (HEALPix has some)
        for x in (SphericalFrontend(cube, g)(img).x, SphericalFrontend(cube, g)(img.astype(np.float64)).x):
            np.testing.assert_allclose(x[clear, 0].numpy(), colours[face[clear]], atol=1e-4)
        assert clear.mean() > 0.99


def test_a_panorama_through_a_cube_map_and_back():
    img = _smooth_panorama(512)
    pano = Equirectangular(512, 256)
    for layout in LAYOUTS:
        back = render(render(img, pano, Cubemap(128, layout)), Cubemap(128, layout), pano)
        # two bilinear resamplings of a smooth picture (3.3; a turned panorama's: 2.0), not
        # worse along the faces' seams
        assert np.abs(back - img).mean() < 4


def test_cube_maps_save_resize_and_refuse(tmp_path):
    cube = Cubemap(64, "dice")
    cameras.save(cube, tmp_path / "cube.yaml")
    loaded = cameras.load(tmp_path / "cube.yaml")
    assert isinstance(loaded, Cubemap) and loaded.key() == cube.key()
    assert cube.resized(128, 96).params() == {"size": 32, "layout": "dice"}
    with pytest.raises(ValueError, match="4 by 3 square faces"):
        cube.resized(128, 64)
    with pytest.raises(ValueError, match="unknown cube map layout"):
        Cubemap(8, "cross")
    with pytest.raises(ValueError, match="whole number of pixels"):
        Cubemap(7.5)


@pytest.mark.parametrize("camera", [Cubemap(8, "horizon"), Cubemap(8, "dice"), Equirectangular(32, 16),
                                    Equirectangular(32, 16, lat_range=(-1.0, 0.5), lon_range=(-2.0, 2.0)),
                                    Cubemap(8, "dice").with_fov(200), Equirectangular(32, 16).with_fov(120)],
                         ids=["horizon", "dice", "panorama", "crop", "dice-fov", "panorama-fov"])
def test_pixels_with_rays_are_those_that_unproject(camera):
    """The shortcuts (no unprojection where every face's or the panorama's pixels have rays;
    one face's rays turned onto each face) say what unprojecting every pixel says."""
    rays, want = camera.unproject(camera.pixel_grid())
    assert np.array_equal(camera.pixels_with_rays(), want) and (~want).any() == (
        camera.fov_limit is not None or camera.model == "cubemap" and camera.layout == "dice")
    fast, valid = camera.pixel_rays()
    assert np.array_equal(valid, want) and np.isnan(fast[~want]).all()
    np.testing.assert_allclose(fast[want], rays[want], atol=1e-15, rtol=0)
