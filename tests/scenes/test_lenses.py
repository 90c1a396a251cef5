"""The protocols' three lenses: their sizes, fields of view and where they look."""

import math

import numpy as np
import pytest

from usf_graph.scenes.lenses import protocol_cameras


@pytest.mark.parametrize("size", [16, 33])
def test_the_protocol_lenses_sizes_fields_of_view_and_direction(size):
    cams = protocol_cameras(size)
    pano, fish, pin = cams["equirectangular"], cams["fisheye190"], cams["pinhole90"]
    assert [(c.width, c.height) for c in (pano, fish, pin)] == [(2 * size, size), (size, size), (size, size)]
    c = (size - 1) / 2
    sides = np.array([[-0.5, c], [size - 0.5, c], [c, -0.5], [c, size - 0.5]])  # the sides' middles
    for cam, half in ((fish, 95.0), (pin, 45.0)):  # each side of the image at half the field
        rays, ok = cam.unproject(sides)
        assert ok.all()
        np.testing.assert_allclose(np.degrees(np.arccos(rays[:, 2])), half, atol=1e-9)
    assert fish.fov_limit == pytest.approx(math.radians(95), rel=1e-15)
    for cam in cams.values():  # the image's centre looks forward, along the sphere's +x
        ray, ok = cam.unproject(np.array([(cam.width - 1) / 2, (cam.height - 1) / 2]))
        np.testing.assert_allclose(cam.rotation @ ray, [1.0, 0.0, 0.0], atol=1e-12)
