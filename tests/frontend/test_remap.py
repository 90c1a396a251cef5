"""Remap, the cv2.remap fast path: which images take it, and which points it recomputes
exactly (its outputs against the tables: test_frontend.py and test_reimage.py)."""

import numpy as np
import pytest
import torch

from usf_graph import cameras, grids
from usf_graph.frontend.interpolation import bilinear_entries, valid_entries, valid_pixels
from usf_graph.frontend.remap import Remap


def test_accepts_numpy_images_of_cv2_types_with_up_to_four_channels():
    assert Remap.accepts(np.zeros((4, 4, 4), np.uint8))  # RGBA
    for dtype in (np.uint16, np.int16, np.float32):
        assert Remap.accepts(np.zeros((4, 4, 1), dtype))
    assert not Remap.accepts(np.zeros((4, 4, 5), np.uint8))
    assert not Remap.accepts(np.zeros((4, 4, 3), np.float64))  # float64 stays exact: the table
    assert not Remap.accepts(np.zeros((4, 4, 3), np.int32))
    assert not Remap.accepts(torch.zeros(4, 4, 3))


@pytest.mark.parametrize("fov", [190.0, 150.0])
def test_only_points_next_to_unreadable_pixels_are_recomputed(fov):
    """A fisheye past its image circle and a robot's body in view: the exact recomputation
    takes the points with an unreadable pixel among their four (at least those where OpenCV
    gives it weight), no others; and a point is reached where its readable pixels have
    weight in the exact table."""
    fish = cameras.KannalaBrandt(20.0, 20.0, 31.5, 31.5, 64, 64, k=(0.0, 0.0, 0.0, 0.0)).with_fov(fov)
    body = np.ones((64, 64), bool)
    body[40:, 20:44] = False
    valid = valid_pixels(fish, body)
    assert 0.3 < valid.mean() < 0.95
    uv, seen = fish.sees(grids.icosahedral(6).pos.numpy())
    r = Remap(fish, uv, seen, "bilinear", valid)
    idx, w = bilinear_entries(fish, uv, seen)
    bad = ~valid.ravel()[idx]  # [M, 4]
    near_any = seen & bad.any(1)
    weighted = seen & ((w * bad).sum(1) > 1 / 16)  # OpenCV's weights: steps of 1/32 a side
    border = np.zeros(len(seen), bool)
    border[r._border[0]] = True
    assert weighted.sum() > 100
    assert np.array_equal(border & weighted, weighted) and np.array_equal(border & near_any, border)
    exact = valid_entries(fish, idx, w, valid=valid).sum(1) > 0
    assert (seen & ~exact).sum() > 10  # points inside the body: none of their pixels readable
    assert np.array_equal(r.reached, seen & exact)
    assert r.restricted(np.zeros(len(seen), bool))._border is None


def test_a_wholly_readable_image_has_no_border():
    pano = cameras.Equirectangular(64, 32)
    uv, seen = pano.sees(grids.icosahedral(3).pos.numpy())
    r = Remap(pano, uv, seen, "bilinear", np.ones((32, 64), bool))
    assert r._border is None and np.array_equal(r.reached, seen) and seen.all()
