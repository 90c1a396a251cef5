"""Plots put each value where its point is."""

import matplotlib.pyplot as plt
import numpy as np
import torch

from usf_graph import grids
from usf_graph.geometry import to_latlon
from usf_graph.viz import mollweide, plot_sphere


def test_mollweide_places_points_at_their_lat_lon_and_greys_out_hidden_ones():
    g = grids.icosahedral(2)
    vals = g.pos[:, 2].clone()  # z
    mask = g.pos[:, 0] > 0
    fig = plt.figure()
    ax = fig.add_subplot(projection="mollweide")
    mollweide(ax, g.pos, vals, mask)
    hidden, shown = ax.collections
    lat, lon = to_latlon(g.pos.numpy())
    m = mask.numpy()
    np.testing.assert_allclose(shown.get_offsets(), np.c_[lon[m], lat[m]], atol=1e-12)
    np.testing.assert_allclose(hidden.get_offsets(), np.c_[lon[~m], lat[~m]], atol=1e-12)
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
