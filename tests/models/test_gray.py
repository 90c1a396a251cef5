"""Models for mono cameras (``gray=True``): they read their input's luma and nothing else,
the up estimate included, and the setting survives the config round trip."""

import cv2
import numpy as np
import pytest
import torch

from usf_graph import grids
from usf_graph.models import (
    PlanarDeepLab,
    PlanarDetector,
    PlanarUNet,
    SphericalDeepLabV3,
    SphericalDetector,
    SphericalUNet,
)
from usf_graph.nn.colour import LUMA, grayscale

SPHERICAL = [
    (SphericalUNet, dict(num_classes=4, level=3, channels=(4, 6), pairs=2, gravity=True)),
    (SphericalDeepLabV3, dict(num_classes=4, level=3, channels=(4, 6), aspp_channels=8,
                              rates=(2,), low_channels=4, pairs=0, gravity=True, upright=True,
                              up_fields=2, upright_convs=2)),
    (SphericalDetector, dict(num_classes=3, input_level=3, head_level=2, min_level=1,
                             channels=(4, 6, 8), pairs=2, gradient_fields=2, gravity=True,
                             upright=True, up_fields=2)),
]
PLANAR = [(PlanarUNet, dict(num_classes=4, channels=(4, 6))),
          (PlanarDeepLab, dict(num_classes=4, channels=(4, 6), aspp_channels=4, rates=(2,))),
          (PlanarDetector, dict(num_classes=3, height=16, width=32, channels=(4, 6)))]


def _flat(out):
    """Every tensor of a model's output, in a fixed order."""
    if isinstance(out, torch.Tensor):
        return [out]
    if isinstance(out, dict):
        return [t for k in sorted(out) for t in _flat(out[k])]
    if isinstance(out, (tuple, list)):
        return [t for o in out for t in _flat(o)]
    return []


def _pair(cls, kw, seed=0):
    """A gray model and its colour twin with the same weights, in float64, evaluating."""
    torch.manual_seed(seed)
    gray = cls(**kw, gray=True).double().eval()
    colour = cls(**kw).double().eval()
    colour.load_state_dict(gray.state_dict())  # gray adds no weights
    return gray, colour


def _input(cls, kw, seed):
    g = torch.Generator().manual_seed(seed)
    if cls in (PlanarUNet, PlanarDeepLab, PlanarDetector):
        return torch.rand(2, 3, kw.get("height", 16), kw.get("width", 32), generator=g,
                          dtype=torch.float64), None, 1
    n = len(grids.icosahedral(kw.get("level", kw.get("input_level"))).pos)
    mask = torch.rand(n, generator=g) < 0.6  # a field of view: new each call
    return torch.rand(2, n, 3, generator=g, dtype=torch.float64), mask, -1


@pytest.mark.parametrize("cls,kw", SPHERICAL + PLANAR)
def test_a_gray_model_is_its_colour_twin_reading_the_luma(cls, kw):
    gray, colour = _pair(cls, kw)
    assert gray.config["gray"] is True and cls.from_config(gray.config).gray is True
    for seed in (1, 2):
        x, mask, dim = _input(cls, kw, seed)
        with torch.no_grad():
            got = _flat(gray(x, mask))
            luma = _flat(colour(grayscale(x, dim), mask))
            col = _flat(colour(x, mask))
            # a change of colour at constant luma changes nothing
            shape = [1] * x.dim()
            shape[dim] = 3
            chroma = torch.tensor([LUMA[2], 0.0, -LUMA[0]], dtype=x.dtype).view(shape)
            shifted = _flat(gray(x + 0.2 * chroma, mask))
        assert len(got) == len(luma) > 0
        for a, b, c in zip(got, luma, shifted):
            torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
            torch.testing.assert_close(c, a, rtol=0, atol=1e-12)
        assert max(float((a - b).abs().max()) for a, b in zip(got, col)
                   if a.is_floating_point()) > 1e-3  # the colour twin does see colour


@pytest.mark.parametrize("cls,kw", SPHERICAL)
def test_the_up_estimate_reads_the_luma_when_called_alone(cls, kw):
    # the up estimate is trained and read alone too (train.gravity.pretrain_up, up='lines')
    gray, colour = _pair(cls, kw)
    x, mask, _ = _input(cls, kw, 3)
    with torch.no_grad():
        a = gray.gravity(x, mask)
        b = colour.gravity(grayscale(x), mask)
    assert gray.gravity.gray and not colour.gravity.gray
    for k in ("up", "logits"):
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=1e-12)


def test_grayscale_is_opencvs_luma():
    """:func:`grayscale` is ``cv2.cvtColor(..., COLOR_RGB2GRAY)`` on any channel axis."""
    rgb = np.random.default_rng(0).random((5, 7, 3), dtype=np.float32)
    want = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    got = grayscale(torch.as_tensor(rgb))
    np.testing.assert_allclose(got.numpy(), np.repeat(want[..., None], 3, -1), rtol=0, atol=1e-6)
    first = grayscale(torch.as_tensor(rgb).permute(2, 0, 1), dim=0)
    np.testing.assert_allclose(first.numpy(), np.repeat(want[None], 3, 0), rtol=0, atol=1e-6)


def test_gray_needs_rgb_inputs():
    for cls, kw in [SPHERICAL[0], PLANAR[0]]:
        with pytest.raises(ValueError, match="in_channels=3, got 1"):
            cls(**kw, in_channels=1, gray=True)
    gray, _ = _pair(*SPHERICAL[0])
    with pytest.raises(ValueError, match="3 channels"):
        gray(torch.zeros(1, len(gray.gravity.view_pos), 1, dtype=torch.float64))


@pytest.mark.parametrize("cls,kw", [SPHERICAL[1], PLANAR[2]])
def test_read_gray_makes_a_colour_model_its_gray_twin(cls, kw):
    from usf_graph.nn.colour import read_gray

    gray, colour = _pair(cls, kw)
    assert read_gray(colour) >= 2 and not colour.config["gray"]  # the model and what it holds
    x, mask, _ = _input(cls, kw, 4)
    with torch.no_grad():
        for a, b in zip(_flat(colour(x, mask)), _flat(gray(x, mask))):
            torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert read_gray(torch.nn.Linear(3, 3)) == 0
    if hasattr(colour, "refined"):  # resolution transfer keeps reading gray
        finer, twin = colour.refined(1), gray.refined(1)
        assert finer.gray and finer.gravity.gray
        x = torch.rand(1, len(finer.gravity.view_pos), 3, dtype=torch.float64)
        with torch.no_grad():
            torch.testing.assert_close(finer(x), twin(x), rtol=0, atol=0)
