"""Cube maps: py360convert's faces, order and layouts, FFmpeg's (its v360 filter's c6x1,
c3x2 and YouTube's equi-angular eac); each face the pinhole it is; points sampled on their
own face; the whole sphere once."""

import math
from fractions import Fraction

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from usf_graph import cameras, grids
from usf_graph.cameras import Cubemap, EquiAngularCubemap, Equirectangular, cube_faces
from usf_graph.cameras.cubemap import EAC_CELLS, FACES, LAYOUTS, face_rotation
from usf_graph.frontend import SphericalFrontend, render
from usf_graph.viz import labelled_panorama


def _smooth_panorama(w: int = 1024) -> np.ndarray:
    """The labelled test panorama, blurred: a smooth picture that still tells faces apart."""
    return cv2.GaussianBlur((255 * labelled_panorama(w, w // 2)).astype(np.float64), (0, 0), 4)


def _faces_agree(ours, theirs, cells, size, tol, corners=None):
    """Each face of ``ours`` (in ``cells``, ``size`` pixels square; or ``size`` square
    crops at the pixels ``corners``) is ``theirs``' within ``tol`` grey levels on average,
    10 times farther from every other face and its mirror images, 5 times from its turns (a
    face of the test picture can look much like itself upside down)."""
    corners = corners or [(c * size, r * size) for c, r in cells]

    def face(a, k):
        u, v = corners[k]
        return a[v:v + size, u:u + size]

    for k in range(6):
        mine, same = face(ours, k), np.abs(face(ours, k) - face(theirs, k)).mean()
        others = [np.abs(mine - face(theirs, j)).mean() for j in range(6) if j != k]
        flips = [np.abs(mine - f).mean() for f in (face(theirs, k)[::-1], face(theirs, k)[:, ::-1])]
        turns = [np.abs(mine - np.rot90(face(theirs, k), q)).mean() for q in (1, 2, 3)]
        assert same < tol and min(others + flips) > 10 * same and min(turns) > 5 * same, \
            (FACES[k], same, others, flips, turns)


@pytest.mark.parametrize("layout", ["horizon", "dice"])
def test_faces_order_and_layout_are_py360converts(layout):
    """The panorama re-imaged into our cube map and py360convert's e2c agree face by face
    (its faces' pixels sit edge to edge, ours at half-pixel offsets: a 1/128 scale apart)."""
    py360convert = pytest.importorskip("py360convert")
    img = _smooth_panorama()
    cube = Cubemap(128, layout)
    ours = render(img, Equirectangular(1024, 512), cube)
    theirs = py360convert.e2c(img, face_w=128, mode="bilinear", cube_format=layout)
    assert ours.shape == theirs.shape == (cube.height, cube.width, 3)
    _faces_agree(ours, theirs, LAYOUTS[layout].cells, 128, 2.5)


def _ffmpeg_v360(img: np.ndarray, args: str) -> np.ndarray:
    """FFmpeg's v360 filter (through PyAV) on an RGB uint8 image."""
    av = pytest.importorskip("av")
    graph = av.filter.Graph()
    src = graph.add_buffer(width=img.shape[1], height=img.shape[0], format="rgb24",
                           time_base=Fraction(1, 25))
    v360, sink = graph.add("v360", args), graph.add("buffersink")
    src.link_to(v360)
    v360.link_to(sink)
    graph.configure()
    frame = av.VideoFrame.from_ndarray(img, format="rgb24")
    frame.pts = 0
    src.push(frame)
    return sink.pull().to_ndarray(format="rgb24")


@pytest.mark.parametrize("layout", ["c6x1", "c3x2"])
def test_ffmpeg_layouts_are_ffmpegs_both_ways(layout):
    """FFmpeg's v360 filter (the tool 360 video is converted with) and ours agree, face by
    face, from a panorama into its layout and back from ours: faces, order, orientation."""
    img = np.clip(_smooth_panorama(), 0, 255).astype(np.uint8)
    cube = Cubemap(128, layout)
    ours = render(img, Equirectangular(1024, 512), cube)
    theirs = _ffmpeg_v360(img, f"input=e:output={layout}:interp=linear:w={cube.width}:h={cube.height}")
    _faces_agree(ours, theirs.astype(np.float64), LAYOUTS[layout].cells, 128, 2.5)
    back = _ffmpeg_v360(np.clip(ours, 0, 255).astype(np.uint8), f"input={layout}:output=e:interp=linear:w=1024:h=512")
    assert np.abs(back.astype(np.float64) - img)[32:-32].mean() < 3  # the poles' rows: a point each


@pytest.mark.parametrize("size", [(384, 256), (1155, 770)])
def test_equiangular_cubemap_is_ffmpegs_eac_both_ways(size):
    """YouTube's EAC as FFmpeg's v360 reads and writes it: its faces, their turns, the
    padding and the equi-angular spacing, pixel by pixel on the faces (the padding's
    pixels have no ray here), from a panorama and back, at whole and fractional face sizes."""
    img = np.clip(_smooth_panorama(), 0, 255).astype(np.uint8)
    eac = EquiAngularCubemap(*size)
    ours = render(img, Equirectangular(1024, 512), eac).astype(np.float64)
    theirs = _ffmpeg_v360(img, f"input=e:output=eac:interp=linear:w={eac.width}:h={eac.height}").astype(np.float64)
    faces = eac.pixels_with_rays()
    assert 0.9 < faces.mean() < 1 and not faces[:, :2].any() and not faces[:2].any()
    err = np.abs(ours - theirs)[faces].mean()
    assert err < 1.5, err
    # each cell is that face, turned as FFmpeg turns it (on whole-pixel crops of the cells)
    fw, fh = eac.face_shape
    crops = [(int(math.ceil(2 + c * fw)), int(math.ceil(r * eac.height / 2 + 2))) for c, r in EAC_CELLS]
    n = int(min(fw, fh)) - 2
    _faces_agree(ours, theirs, None, n, 2.5, corners=crops)
    back = _ffmpeg_v360(np.clip(ours, 0, 255).astype(np.uint8), "input=eac:output=e:interp=linear:w=1024:h=512")
    assert np.abs(back.astype(np.float64) - img)[32:-32].mean() < 3  # the poles' rows: a point each
    # FFmpeg's EAC image read back by each: the same panorama
    theirs = theirs.astype(np.uint8)
    read = render(theirs, eac, Equirectangular(1024, 512)).astype(np.float64)
    assert np.abs(read - _ffmpeg_v360(theirs, "input=eac:output=e:interp=linear:w=1024:h=512"))[32:-32].mean() < 2


def test_equiangular_cubemap_faces_are_even_in_angle():
    """Across an EAC face, equal steps in pixels are equal steps in angle; across a plain
    cube face, equal steps in the angle's tangent."""
    eac = EquiAngularCubemap(3 * 90 + 4, 2 * 90 + 8)  # faces 90 pixels square
    rays, _ = eac.pixel_rays()
    row = rays[2 + 45, 2 + 90:2 + 180] @ face_rotation("front")  # the front face's middle row
    np.testing.assert_allclose(np.arctan2(row[:, 0], row[:, 2]), np.radians(np.arange(90) - 44.5), atol=1e-12)
    rays, _ = Cubemap(90, "c3x2").pixel_rays()
    row = rays[90 + 45, 90:180] @ face_rotation("front")
    np.testing.assert_allclose(row[:, 0] / row[:, 2], (np.arange(90) - 44.5) / 45, atol=1e-12)


def test_equiangular_cubemap_rays_round_trip_and_cover_the_sphere(tmp_path):
    rng = np.random.default_rng(0)
    rays = rng.normal(size=(2000, 3))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    for eac in (EquiAngularCubemap(1155, 770), EquiAngularCubemap(96, 64, padding=0)):
        uv, ok = eac.project(rays)
        back, ok2 = eac.unproject(uv)
        assert ok.all() and ok2.all()
        np.testing.assert_allclose(back, rays, atol=1e-12)
        assert math.isclose(eac.solid_angle(), 4 * math.pi, rel_tol=1e-3)
    cameras.save(EquiAngularCubemap(1155, 770), tmp_path / "eac.yaml")
    loaded = cameras.load(tmp_path / "eac.yaml")
    assert isinstance(loaded, EquiAngularCubemap)
    assert loaded.params() == {"width": 1155, "height": 770, "padding": 2.0}
    assert EquiAngularCubemap(1155, 770).resized(578, 385).padding == pytest.approx(2 * 578 / 1155)
    with pytest.raises(ValueError, match="one factor both ways"):
        EquiAngularCubemap(1155, 770).resized(578, 770)
    with pytest.raises(ValueError, match="padding must be"):
        EquiAngularCubemap(30, 20, padding=3)


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


@pytest.mark.parametrize("camera", [Cubemap(8, "horizon"), Cubemap(8, "dice"), Cubemap(8, "c3x2"),
                                    EquiAngularCubemap(40, 30)], ids=["horizon", "dice", "c3x2", "eac"])
def test_points_off_the_layout_have_no_ray(camera):
    """Past any edge of the image, by less than a face, a point lies on no face: the
    nearest face's cell is not stretched to reach it."""
    w, h = camera.width, camera.height
    off = np.array([[w + 1.0, 1.0], [1.0, h + 1.0], [w + 1.0, h + 1.0], [-2.0, 1.0], [1.0, -2.0]])
    rays, ok = camera.unproject(off)
    assert not ok.any() and np.isnan(rays).all()


def test_smallest_cube_maps_and_the_widest_padding():
    """A face of 2 pixels and an EAC image of 6 are allowed; padding must leave most of a
    face both across (a third of the width) and down (half the height)."""
    assert Cubemap(2).width == 12 and EquiAngularCubemap(6, 6, padding=0).face_shape == (2, 3)
    for w, h in ((30, 40), (40, 20)):  # the narrower face across, then down: 10 pixels
        EquiAngularCubemap(w, h, padding=2.4)
        with pytest.raises(ValueError, match="padding must be"):
            EquiAngularCubemap(w, h, padding=2.6)


@pytest.mark.parametrize("camera", [Cubemap(8, "horizon"), Cubemap(8, "dice"), EquiAngularCubemap(40, 30),
                                    Equirectangular(32, 16),
                                    Equirectangular(32, 16, lat_range=(-1.0, 0.5), lon_range=(-2.0, 2.0)),
                                    Cubemap(8, "dice").with_fov(200), Equirectangular(32, 16).with_fov(120)],
                         ids=["horizon", "dice", "eac", "panorama", "crop", "dice-fov", "panorama-fov"])
def test_pixels_with_rays_are_those_that_unproject(camera):
    """The shortcuts (no unprojection where every face's or the panorama's pixels have rays;
    one face's rays turned onto each face) say what unprojecting every pixel says."""
    rays, want = camera.unproject(camera.pixel_grid())
    assert np.array_equal(camera.pixels_with_rays(), want) and (~want).any() == (
        camera.fov_limit is not None or camera.model == "eac" or  # its padding
        camera.model == "cubemap" and camera.layout == "dice")
    fast, valid = camera.pixel_rays()
    assert np.array_equal(valid, want) and np.isnan(fast[~want]).all()
    np.testing.assert_allclose(fast[want], rays[want], atol=1e-15, rtol=0)
