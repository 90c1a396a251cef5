"""Gray inputs: the luma is OpenCV's, a gray image passes unchanged, bad shapes are refused."""

import cv2
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from usf_graph.nn.colour import LUMA, check_gray, grayscale


def test_luma_is_opencvs_on_a_real_photograph():
    from skimage import data

    rgb = data.astronaut()[::8, ::8]  # uint8 [64, 64, 3]
    want = cv2.cvtColor(rgb.astype(np.float32) / 255, cv2.COLOR_RGB2GRAY)
    got = grayscale(torch.as_tensor(rgb, dtype=torch.float64) / 255)
    assert got.shape == rgb.shape
    for c in range(3):  # each channel holds the luma
        np.testing.assert_allclose(got[..., c].numpy(), want, rtol=0, atol=1e-6)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2 ** 31 - 1), st.sampled_from([0, 1, 2, -1]))
def test_gray_images_pass_unchanged_and_chroma_is_dropped(seed, dim):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(2, 3, 4, 5, generator=g, dtype=torch.float64).movedim(1, dim)
    y = grayscale(x, dim)
    assert y.shape == x.shape
    torch.testing.assert_close(grayscale(y, dim), y, rtol=0, atol=1e-15)  # gray stays gray
    shape = [1] * 4
    shape[dim] = 3
    # a change of colour at constant luma is invisible
    chroma = torch.tensor([LUMA[1], -LUMA[0], 0.0], dtype=torch.float64).view(shape)
    torch.testing.assert_close(grayscale(x + 0.3 * chroma, dim), y, rtol=0, atol=1e-15)
    w = torch.tensor(LUMA, dtype=torch.float64).view(shape)
    torch.testing.assert_close(y.narrow(dim, 0, 1), (x * w).sum(dim, keepdim=True), rtol=0, atol=0)


def test_bad_shapes_and_configs_are_refused():
    with pytest.raises(ValueError, match="3 channels along dim -1"):
        grayscale(torch.zeros(2, 4))
    with pytest.raises(ValueError, match="in_channels=3, got 1"):
        check_gray(True, 1)
    assert check_gray(False, 1) is False and check_gray(1, 3) is True
