"""Segmentation models: equivariant per-point logits (exact under grid symmetries, in
float64), resolution transfer, planar baselines, bad inputs."""

import numpy as np
import pytest
import torch

from usf_graph import grids
from usf_graph.geometry import rotation_from_axis_angle
from usf_graph.models import PlanarDeepLab, PlanarUNet, SphericalDeepLabV3, SphericalUNet
from usf_graph.models.planar_seg import conv_block
from usf_graph.models.stages import ConvStage, level_spacing
from usf_graph.models.unet import SphericalBackbone
from usf_graph.nn import UprightConv
from usf_graph.testing import assert_equivariant, smooth_signal, symmetry_permutation

UNET = dict(num_classes=5, level=3, channels=(4, 6, 8), pairs=2, gravity=True)
DEEPLAB = dict(num_classes=5, level=3, channels=(4, 6), aspp_channels=8, rates=(2, 3),
               low_channels=4, pairs=2, gravity=True)


def _symmetry(level):
    pos = grids.icosahedral(level).pos
    axis = pos[0] / pos[0].norm()  # a 5-fold axis through a vertex
    return pos, axis, rotation_from_axis_angle(axis, torch.tensor(2 * np.pi / 5, dtype=torch.float64))


def _signal(pos, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.as_tensor(smooth_signal(pos.numpy()))[None] + \
        0.3 * torch.randn(2, len(pos), 3, generator=g, dtype=torch.float64)


@pytest.mark.parametrize("cls,kw", [(SphericalUNet, UNET), (SphericalUNet, {**UNET, "head_depth": 1}),
                                    (SphericalDeepLabV3, DEEPLAB),
                                    (SphericalUNet, {**UNET, "upright": True}),
                                    (SphericalUNet, {**UNET, "upright": True, "pairs": 0, "up_fields": 2}),
                                    (SphericalDeepLabV3, {**DEEPLAB, "upright": True}),
                                    (SphericalUNet, {**UNET, "upright": True, "upright_convs": 3,
                                                     "head_depth": 1}),
                                    (SphericalDeepLabV3, {**DEEPLAB, "upright": True, "upright_convs": 3})])
def test_logits_move_with_the_rotation(cls, kw):
    torch.manual_seed(0)
    m = cls(**kw).double().eval()
    for mod in m.modules():  # non-trivial running statistics
        if hasattr(mod, "running_var"):
            mod.running_mean.uniform_(-0.2, 0.2)
            mod.running_var.uniform_(0.5, 2.0)
    with torch.no_grad():  # peaked up scores, so that the estimate is well defined
        m.gravity.head.score.weight.mul_(50)
    pos, axis, R = _symmetry(3)
    x = _signal(pos)
    err = assert_equivariant(m, (x,), pos, R, atol=1e-9)
    assert err < 1e-9
    assert m(x).std() > 1e-3  # not a constant map
    # a field of view symmetric about the axis (a cap): hidden points stay out exactly
    mask = pos @ axis > -0.3
    # (masked normalizations of small sums, and the gravity head's sum over the visible
    # cap, amplify rounding to ~1e-6; a broken symmetry shows at the output's scale)
    assert_equivariant(lambda x, mk: m(x, mk), (x, mask), pos, R, atol=1e-5)
    # the estimated up rotates with the input
    up = m(x, mask, return_gravity=True)[1]["up"]
    xr = torch.empty_like(x)
    xr[:, symmetry_permutation(pos, R)] = x
    up_r = m(xr, mask, return_gravity=True)[1]["up"]
    assert torch.allclose(up_r, up @ R.T, atol=1e-9) and torch.allclose(up.norm(dim=-1), torch.ones(2, dtype=torch.float64))
    # and the hidden part of the input does not matter
    y = x.clone()
    y[:, ~mask] = 5.0
    assert torch.allclose(m(x, mask)[:, mask], m(y, mask)[:, mask], atol=1e-12)


@pytest.mark.parametrize("cls,kw", [(SphericalUNet, {**UNET, "head_depth": 1}), (SphericalDeepLabV3, DEEPLAB)])
def test_oriented_stages_are_those_on_the_asked_levels(cls, kw):
    """``upright_convs=L``: every conv stage of the segmenter (not its up estimate's) on
    level L and coarser is made of UprightConvs, the finer ones of distance-only convs."""
    def stages(m):
        return [mod for name, mod in m.named_modules()
                if isinstance(mod, ConvStage) and not name.startswith("gravity")]
    torch.manual_seed(0)
    m = cls(**{**kw, "upright": True, "upright_convs": 2}).double().eval()
    by_level = {}
    for st in stages(m):
        n = len(st.area)
        by_level.setdefault(n, set()).add(st.upright)
        assert all(isinstance(c, UprightConv) == st.upright for c in st.convs)
    assert by_level[len(grids.icosahedral(2))] == {True} and by_level[len(grids.icosahedral(3))] == {False}
    # the level-3 ones too with upright_convs=3, none with None
    m3 = cls(**{**kw, "upright": True, "upright_convs": 3})
    assert all(st.upright for st in stages(m3)) and not any(st.upright for st in stages(cls(**{**kw, "upright": True})))
    with pytest.raises(ValueError, match="upright_convs reads up"):
        cls(**{**kw, "upright_convs": 3})


@pytest.mark.parametrize("pairs,upright", [(2, False), (0, True), (2, True)])
def test_backbone_is_built_as_its_docstring_says(pairs, upright):
    """Stage s convolves on level input_level - s with radius radius_spacings grid
    spacings; the first pair_stages stages (not the coarsest) add gradient pairs and,
    upright, UpJet fields; pooling and upsampling blur by 0.5 coarse spacings."""
    b = SphericalBackbone(3, input_level=4, out_level=4, min_level=2, channels=(4, 6, 8),
                          radius_spacings=2.5, pairs=pairs, pair_stages=1, upright=upright,
                          up_fields=2)
    h = level_spacing
    assert [c.radius for st in b.down for c in st.convs] == pytest.approx([2.5 * h(lv) for lv in (4, 3, 2)])
    assert [c.radius for st in b.up for c in st.convs] == pytest.approx([2.5 * h(lv) for lv in (3, 4)])
    assert [p.sigma for p in b.pools] == pytest.approx([0.5 * h(3), 0.5 * h(2)])
    assert [p.sigma for p in b.ups] == pytest.approx([0.5 * h(2), 0.5 * h(3)])
    assert (len(b.pairs), len(b.up_pairs)) == (int(pairs > 0), int(upright))
    # everything on the coarsest level with pair_stages covering it: no pairs there
    b3 = SphericalBackbone(3, input_level=3, out_level=3, min_level=2, channels=(4, 6),
                           pairs=2, pair_stages=5)
    assert len(b3.pairs) == 1 and b3.skip_channels == [4 + 2 * 2, 6]


def test_deeplab_is_built_as_its_docstring_says():
    """ASPP on aspp_level: atrous branches of radius rates spacings; Gaussian upsampling by
    half an aspp spacing; the decoder's kernel radius_spacings spacings of the output level."""
    m = SphericalDeepLabV3(num_classes=3, level=4, channels=(4, 6, 8), aspp_channels=4,
                           rates=(2, 5), low_channels=4, radius_spacings=2.5)
    h = level_spacing
    assert m.config["aspp_level"] == 2 and len(m.backbone.grids[2].pos) == 162
    assert [c.radius for st in m.atrous for c in st.convs] == pytest.approx([2 * h(2), 5 * h(2)])
    assert m.up.sigma == pytest.approx(0.5 * h(2))
    assert [c.radius for c in m.decoder.convs] == pytest.approx([2.5 * h(4)])
    assert m.fuse.lin.in_features == 4 * 4  # point, two atrous, image pooling


@pytest.mark.parametrize("cls,kw", [(SphericalUNet, UNET), (SphericalDeepLabV3, DEEPLAB)])
def test_refined_model_computes_nearly_the_same_function(cls, kw):
    torch.manual_seed(1)
    m = cls(**kw).double().eval()  # level 3, refined to 4 (5 took 5x longer, no more checked)
    fine = m.refined()  # one level finer by default
    assert fine.num_points == len(grids.icosahedral(4)) and fine.config["refine"] == 1
    assert (m.input_grid, fine.input_grid) == ("icosahedral:3", "icosahedral:4")
    coarse_pos, fine_pos = grids.icosahedral(3).pos, grids.icosahedral(4).pos
    f = lambda p: torch.as_tensor(smooth_signal(p.numpy()))[None]  # noqa: E731
    with torch.no_grad():
        a, b = m(f(coarse_pos)), fine(f(fine_pos))[:, : len(coarse_pos)]  # nested grids
    rel = (a - b).norm() / a.norm()
    assert rel < 0.1, rel  # 0.022 (U-Net), 0.0015 (DeepLab)
    # another network with the same architecture differs far more: the weights carried over
    other = cls(**kw).double().eval().refined(1)
    with torch.no_grad():
        c = other(f(fine_pos))[:, : len(coarse_pos)]
    assert (a - c).norm() / a.norm() > 3 * rel


def test_planar_models_shapes_and_errors():
    x = torch.rand(2, 3, 32, 64)
    assert PlanarUNet(5, channels=(4, 8, 8))(x).shape == (2, 5, 32, 64)
    assert PlanarUNet(5, channels=(4, 8, 8), out_stride=2)(x).shape == (2, 5, 16, 32)
    assert PlanarDeepLab(5, channels=(4, 8, 8), aspp_channels=8)(x).shape == (2, 5, 32, 64)
    with pytest.raises(ValueError, match="divisible by 4"):
        PlanarUNet(5, channels=(4, 8, 8))(torch.rand(1, 3, 30, 64))
    with pytest.raises(ValueError, match="out_stride"):
        PlanarUNet(5, channels=(4, 8), out_stride=4)


def test_planar_defaults_fit_stanford_2d3ds():
    from usf_graph.scenes import SEMANTIC_CLASSES

    assert len(SEMANTIC_CLASSES) == 13
    assert PlanarUNet().head[-1].out_channels == PlanarDeepLab().head.out_channels == 13


def test_planar_models_commute_with_shifts_by_their_pooling_stride():
    """Away from the borders (zero padding), shifting the image by 8 pixels (a multiple of
    the 4x pooling) shifts the logits by 8: the bilinear upsampling scales by exactly 2 or 4
    with pixel centres aligned (``align_corners=True`` stretches by 15/7 and breaks this)."""
    torch.manual_seed(0)
    deeplab = PlanarDeepLab(3, channels=(4, 8, 8), aspp_channels=4, rates=(2,))
    deeplab.aspp.pool[0].weight.data.zero_()  # the image pooling reads the borders too
    for m in (PlanarUNet(3, channels=(4, 8, 8)), PlanarUNet(3, channels=(4, 8, 8), out_stride=2),
              deeplab):
        m = m.double().eval()
        s = m.config.get("out_stride", 1)
        x = torch.rand(1, 3, 16, 128, dtype=torch.float64)
        a, b = m(x), m(torch.roll(x, 8, -1))
        inner = slice(48 // s, 80 // s)  # the receptive field (< 40 pixels) misses the borders
        shifted = torch.roll(a, 8 // s, -1)
        torch.testing.assert_close(b[..., inner], shifted[..., inner], rtol=0, atol=1e-12)
        assert (b - shifted).abs().max() > 1e-5  # the borders do differ: zero padding, no wrap


def test_planar_receptive_fields_are_those_of_their_convolutions():
    """One level: three 3x3 convolutions (two, then the head's), so a logit reads the input
    within 3 pixels, no farther; an ASPP branch at rate r reads r pixels away."""
    torch.manual_seed(0)

    def reach(net, c_in, size=31):
        x = torch.rand(1, c_in, size, size, dtype=torch.float64, requires_grad=True)
        net(x)[0, :, size // 2, size // 2].sum().backward()
        r, c = torch.nonzero(x.grad.abs().sum((0, 1)) > 0).T - size // 2
        return int(torch.cat([r, c]).abs().max())

    assert reach(PlanarUNet(3, channels=(4,)).double().eval(), 3) == 3
    for rate in (1, 3):
        conv = conv_block(2, 2, *([rate] if rate > 1 else []))[0].double()  # the default: 1
        assert reach(conv, 2) == rate
    deeplab = PlanarDeepLab(3, channels=(4,), aspp_channels=4, rates=(5,)).double().eval()
    deeplab.aspp.pool[0].weight.data.zero_()  # the image pooling reads everything: not it
    assert reach(deeplab, 3) == 2 + 5 + 1  # two convs, the ASPP's rate, the decoder


def test_spherical_models_reject_bad_input():
    m = SphericalUNet(**UNET)
    n = m.num_points
    with pytest.raises(ValueError, match=r"icosahedral:3"):
        m(torch.zeros(1, n + 1, 3))
    with pytest.raises(ValueError, match=r"icosahedral:4\)"):  # the grid a refined one reads
        SphericalBackbone(3, input_level=3, out_level=3, min_level=2, channels=(4, 6),
                          refine=1)(torch.zeros(1, n, 3))
    x = torch.zeros(1, n, 3)
    x[0, 5, 1] = float("nan")
    with pytest.raises(ValueError, match="x has NaN or inf; lift images with SphericalFrontend"):
        m(x)
    with pytest.raises(ValueError, match="some point visible"):
        m(torch.zeros(1, n, 3), torch.zeros(n, dtype=torch.bool))
    with pytest.raises(ValueError, match="channels needs one entry"):
        SphericalUNet(level=3, min_level=2, channels=(4, 6, 8))
    with pytest.raises(ValueError, match="needs gravity=True"):
        SphericalUNet(**{**UNET, "gravity": False, "upright": True})
    with pytest.raises(ValueError, match="upright backbone needs up"):
        SphericalUNet(**{**UNET, "upright": True}).backbone(torch.zeros(1, n, 4))
    # a known up must be a direction: a zero vector used to surface as "x has NaN"
    for up in (torch.zeros(1, 3), torch.tensor([[0.0, float("nan"), 1.0]]), torch.ones(2, 3)):
        with pytest.raises(ValueError, match="up must be finite, nonzero"):
            m.eval()(torch.zeros(1, n, 3), up=up)
