"""Pixel values: unit_range (what the models read) and to_uint8 (what is shown) agree."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

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
