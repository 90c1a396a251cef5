"""Pixel values: unit_range (what the models read) and to_uint8 (what is shown) agree;
SphericalImages save and load as PyG's own data."""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from usf_graph import SphericalImage
from usf_graph.frontend.image import to_uint8, unit_range


@settings(max_examples=40, deadline=None)
@given(st.sampled_from([np.uint8, np.uint16]).flatmap(
    lambda t: arrays(t, (3, 4, 3), elements=st.integers(0, np.iinfo(t).max))))
def test_to_uint8_shows_what_the_models_read(img):
    """For uint8 and uint16, the shown grey level is the model's [0, 1] value times 255,
    rounded: a uint16 image uses its whole range, not its first 255 levels."""
    want = np.round(unit_range(img).astype(np.float64) * 255)
    assert to_uint8(img).dtype == np.uint8
    assert np.abs(to_uint8(img) - want).max() <= (0 if img.dtype == np.uint8 else 1e-9)


def test_to_uint8_floats_and_refusals():
    a = np.array([[0.0, 0.5, 1.0, 1.7, -0.2, np.nan]], np.float32)
    assert to_uint8(a).tolist() == [[0, 128, 255, 255, 0, 0]]
    assert to_uint8(np.array([65535, 257, 128], np.uint16)).tolist() == [255, 1, 0]
    with pytest.raises(ValueError, match="uint8, uint16 or float"):
        to_uint8(np.zeros(3, np.int32))


def test_an_in_memory_dataset_of_spherical_images_loads_safely(tmp_path):
    """PyG's ``InMemoryDataset`` saves and loads a list of SphericalImages with
    ``torch.load(weights_only=True)``, as it does its own ``Data``, not by falling back to
    unsafe unpickling (PyG warns when it does)."""
    import warnings

    from torch_geometric.data import InMemoryDataset

    from usf_graph import SphericalFrontend, cameras, grids

    fe = SphericalFrontend(cameras.Equirectangular(32, 16), grids.icosahedral(1))
    rng = np.random.default_rng(0)
    imgs = [fe(rng.random((16, 32, 3), np.float32)) for _ in range(2)]

    class Lifted(InMemoryDataset):
        def __init__(self):
            super().__init__(str(tmp_path / "root"))
            self.load(str(tmp_path / "set.pt"))

    InMemoryDataset.save(imgs, str(tmp_path / "set.pt"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds = Lifted()
    assert type(ds[1]) is SphericalImage and len(ds) == 2
    assert torch.equal(ds[1].x, imgs[1].x) and torch.equal(ds[1].mask, imgs[1].mask)
    assert torch.equal(ds[0].edge_dist, imgs[0].edge_dist)


def test_unit_range_takes_floats_in_zero_one_and_refuses_the_rest():
    a = np.array([[0.0, 0.25, 1.0, np.nan]], np.float64)
    out = unit_range(a)
    assert out.dtype == np.float32 and np.array_equal(out, a.astype(np.float32), equal_nan=True)
    assert unit_range(np.array([0, 255], np.uint8)).tolist() == [0.0, 1.0]
    for bad, said in ((np.array([-0.5, 1.0]), r"\[-0.5, 1\]"), (np.array([0.0, 2.0]), r"\[0, 2\]")):
        with pytest.raises(ValueError, match=rf"values in \[0, 1\], got {said}; divide by 255"):
            unit_range(bad)
    with pytest.raises(ValueError, match="image dtype int32 is not supported"):
        unit_range(np.zeros(3, np.int32))


def test_a_spherical_images_latitude_and_longitude_are_its_points():
    from usf_graph.geometry import from_latlon

    rng = np.random.default_rng(3)
    lat, lon = rng.uniform(-1.5, 1.5, 20), rng.uniform(-3.1, 3.1, 20)
    img = SphericalImage(x=torch.zeros(20, 1), pos=torch.as_tensor(from_latlon(lat, lon)))
    np.testing.assert_allclose(img.lat.numpy(), lat, atol=1e-12)
    np.testing.assert_allclose(img.lon.numpy(), lon, atol=1e-12)
