"""Plots put each value where its point is."""

import matplotlib.pyplot as plt
import numpy as np
import pytest
import torch

from tests.helpers import decode_video
from usf_graph import grids
from usf_graph.geometry import to_latlon
from usf_graph.viz import mollweide, plot_sphere


def test_mollweide_shows_the_sphere_from_inside_and_greys_out_hidden_ones():
    g = grids.icosahedral(2)
    vals = g.pos[:, 2].clone()  # z
    mask = g.pos[:, 0] > 0
    fig = plt.figure()
    ax = fig.add_subplot(projection="mollweide")
    mollweide(ax, g.pos, vals, mask)
    hidden, shown = ax.collections
    lat, lon = to_latlon(g.pos.numpy())
    m = mask.numpy()
    # seen from the centre, as the cameras see it: longitude decreases to the right, so the
    # left (+y, lon > 0) is drawn on the left of the map
    np.testing.assert_allclose(shown.get_offsets(), np.c_[-lon[m], lat[m]], atol=1e-12)
    np.testing.assert_allclose(hidden.get_offsets(), np.c_[-lon[~m], lat[~m]], atol=1e-12)
    left = np.argmax(g.pos[:, 1].numpy())  # the +y point
    assert shown.get_offsets()[np.flatnonzero(m) == left].size == 0  # (hidden: x = 0)
    assert hidden.get_offsets()[np.flatnonzero(~m) == left][0, 0] < 0
    np.testing.assert_allclose(shown.get_array(), vals.numpy()[m], atol=1e-12)
    # x > 0 is the front hemisphere: |lon| < pi/2 there
    assert np.abs(shown.get_offsets()[:, 0]).max() < np.pi / 2
    plt.close(fig)


def test_plot_sphere_writes_a_figure(tmp_path):
    g = grids.healpix(4)
    plot_sphere(g.pos, torch.arange(len(g), dtype=torch.float64), path=tmp_path / "s.png",
                title="index")
    assert (tmp_path / "s.png").stat().st_size > 20_000


def test_rgb_signals_are_drawn_in_their_colours():
    g = grids.icosahedral(1)
    rgb = torch.rand(len(g), 3, generator=torch.Generator().manual_seed(0)) * 255  # 8-bit range
    fig = plt.figure()
    ax = fig.add_subplot(projection="mollweide")
    mollweide(ax, g.pos, rgb)
    shown = ax.collections[1]
    top = float(rgb.max())
    np.testing.assert_allclose(shown.get_facecolors()[:, :3], rgb.numpy() / top, atol=1e-6)
    plt.close(fig)


def test_a_lifted_image_is_not_mirrored_in_its_preview():
    from usf_graph import SphericalFrontend, cameras

    cam = cameras.Pinhole(100, 100, 63.5, 63.5, 128, 128)
    img = np.zeros((128, 128), np.float32)
    img[:, 64:] = 1  # the right half of the picture is bright
    g = grids.icosahedral(4)
    fe = SphericalFrontend(cam, g)
    x = fe.lift(img)[:, 0]
    fig = plt.figure()
    ax = fig.add_subplot(projection="mollweide")
    mollweide(ax, g.pos, x, fe.mask)
    _, shown = ax.collections
    xy, v = shown.get_offsets(), shown.get_array()
    bright, dark = xy[v > 0.9], xy[v < 0.1]
    assert len(bright) > 20 and len(dark) > 20
    assert (bright[:, 0] > 0).all() and (dark[:, 0] < 0).all()  # right stays right
    plt.close(fig)


def test_frame_video_writes_what_it_is_given(tmp_path, capsys):
    from usf_graph.viz import FrameVideo

    v = FrameVideo(tmp_path / "a.avi", fps=4)
    frames = [np.full((31, 40, 3), (40 * k, 255 - 40 * k, 100), np.uint8) for k in range(3)]
    for f in frames:
        v.add(f)
    v.add(np.zeros((62, 80, 3), np.uint8))  # another size: resized to the first's
    v.close()
    got, _ = decode_video(tmp_path / "a.avi")
    assert len(got) == 4 and got[0].shape == (32, 40, 3)  # even sizes for the codec
    assert "frames of 40x31 resized to 40x32" in capsys.readouterr().out  # and it says so
    for g, f in zip(got, frames):  # Motion JPEG: colours to a few levels
        assert np.abs(g[4:-4, 4:-4].astype(int) - f[0, 0]).max() < 12
    assert got[3].max() < 12
    with pytest.raises(ValueError, match="write .avi or .mp4"):
        FrameVideo(tmp_path / "a.gif")
    with pytest.raises(ValueError, match="frame rate must be positive"):
        FrameVideo(tmp_path / "a.avi", fps=0)


def test_graticule_lies_where_the_sphere_frame_says():
    """The horizon through a level pinhole is the row of its principal point; a panorama's
    meridians are its columns every 15 degrees and its parallels its rows; a fisheye's red
    edge is its image circle. Nothing is drawn far from every circle."""
    from usf_graph.cameras import Equirectangular, Fisheye, Pinhole
    from usf_graph.viz import HORIZON, VIEW_EDGE, draw_graticule

    pin = Pinhole(256.0, 256.0, 255.5, 191.5, 512, 384)
    out = draw_graticule(np.zeros((384, 512, 3), np.uint8), pin)
    assert out.shape == (384, 512, 3)
    row = out[191:193, 100:400].reshape(-1, 3)
    assert (np.abs(row.astype(int) - HORIZON).max(1) < 40).mean() > 0.9  # the horizon, yellow
    # meridians are vertical lines (lon 15 and 30 at columns 186.9 and 107.7), the 15-degree
    # parallel bends above row 125 there: nothing in between
    assert (out[130:180, 115:180] == 0).all() and (out[197:250, 191:251] == 0).all()
    assert (out[100:300, 186:189].max(-1).max(-1) > 100).mean() > 0.9  # the 15-degree meridian
    pano = Equirectangular(720, 360)
    out = draw_graticule(np.zeros((360, 720), np.float32), pano)  # gray floats too
    cols = out[20:340:7, [179, 180, 359, 360]].max(-1)  # lon 90 and 0: columns 179.5 and 359.5
    assert (cols > 100).all()
    assert (out[124:146, 184:206] == 0).all()  # inside a 15-degree cell (rows 119.5-149.5)
    assert np.all(np.abs(out[179:181, 200:300].astype(int) - HORIZON).max(-1).min(0) < 60)
    assert (out[118:122, 200:300].min(-1).max(0) > 100).all()  # 30 N (antialiased: grey-white)
    fish = Fisheye(100.0, 255.5, 255.5, 512, 512, model="equidistant", fov_deg=180)
    out = draw_graticule(np.zeros((512, 512, 3), np.uint8), fish)
    r = 100.0 * np.pi / 2  # the image circle's radius: 157 pixels
    t = np.linspace(0, 2 * np.pi, 100, endpoint=False)
    on = out[np.round(255.5 + (r - 1) * np.sin(t)).astype(int), np.round(255.5 + (r - 1) * np.cos(t)).astype(int)]
    assert (np.abs(on.astype(int) - VIEW_EDGE).max(1) < 60).mean() > 0.8
    grey = np.random.default_rng(0).integers(0, 256, (512, 512, 3)).astype(np.uint8)
    assert np.array_equal(draw_graticule(grey.astype(np.uint16) * 257, fish),  # 16-bit: its range
                          draw_graticule(grey, fish))
    with pytest.raises(ValueError, match="the camera's"):
        draw_graticule(np.zeros((10, 10, 3), np.uint8), fish)
