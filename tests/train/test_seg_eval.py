"""Predictions of a segmenter in a test set's pixels and points, read with a given up or
with the model's own estimate, and one test set scored."""

import copy

import numpy as np
import pytest
import torch

from usf_graph.train.gravity import split_up, up_report, views_up
from usf_graph.train.seg import make_model, protocol_sets
from usf_graph.train.seg_eval import evaluate_set, predict


@pytest.fixture(scope="module")
def sets(tmp_path_factory):
    root = tmp_path_factory.mktemp("rooms")
    return protocol_sets(root, size=16, level=3, num_train=0, num_test=3, tests=("b", "c"),
                         progress=False)


@pytest.fixture(scope="module")
def net():
    torch.manual_seed(0)
    return make_model("spherical_unet", level=3).eval()


class HeightBands(torch.nn.Module):
    """Labels each point by its height along the up it is handed, in 13 bands: what it
    predicts shows which up reached which view."""

    def __init__(self, pos):
        super().__init__()
        self.register_buffer("pos", pos.double())

    def forward(self, x, mask=None, up=None):
        return bands(self.pos, up.double()).to(x.dtype)


def bands(pos, up):
    """One-hot ``[B, N, 13]`` logits of the height ``pos . up`` of each view's points."""
    height = up @ pos.T  # [B, N]
    return torch.nn.functional.one_hot(((height + 1) * 6.5).long().clamp(0, 12), 13).double()


def test_predict_hands_each_view_its_own_up(sets):
    """One up for every view, or each view its own (the rotated ones, in batches of 2 of
    3): each view's points are labelled by the up it was given, and its pixels are those
    points' labels rendered into the camera, nearest."""
    ds, rot = sets["c"], sets["b"]
    model = HeightBands(ds.grid.pos)
    z = torch.tensor([0.0, 0.0, 1.0])
    pix, points = predict(model, ds, up=z, progress=False)
    logits = bands(ds.grid.pos.double(), z[None].double())[0]
    assert np.array_equal(points, logits.argmax(-1).expand(len(ds), -1).numpy())
    assert pix.shape == (len(ds), *ds.image.shape[1:3]) and pix.dtype == np.uint8
    assert np.array_equal(pix[1], ds.frontend.to_labels(logits, "nearest").numpy())
    assert not (rot.gravity[:, 2] > 0.999).all()  # the views' ups differ
    _, points = predict(model, rot, batch_size=2, up=rot.gravity, progress=False)
    want = bands(rot.grid.pos.double(), rot.gravity.double()).argmax(-1)
    assert np.array_equal(points, want.numpy()) and len(np.unique(points)) > 3


def test_evaluate_set_runs_the_estimate_once_for_prediction_and_report(sets, net):
    """Its pixels are the model's own (the estimate run inside its forward), its report a
    separate run's; given the true up, the report is the estimate's all the same."""
    ds = sets["c"]
    calls = []
    hook = net.gravity.register_forward_hook(lambda *_: calls.append(1))
    r, pix = evaluate_set(net, ds, progress=False)
    hook.remove()
    assert len(calls) == 1 and np.array_equal(pix, predict(net, ds, progress=False)[0])
    assert r["up"] == up_report(net.gravity, ds.x, ds.mask[0], views_up(ds))
    assert evaluate_set(net, ds, progress=False, known_up=True)[0]["up"] == r["up"]
    assert 0 <= r["mIoU"] <= 1 and "sphere_mIoU" in r


def test_a_split_whose_views_see_different_fields_is_refused(sets, net):
    """Prediction and the up estimate run a batch with one field of view: a split of
    several cameras' views (WoodScape's) would be read through its first view's field,
    so it is refused, naming the function that batches by field."""
    mixed = copy.copy(sets["c"])
    mixed.mask = sets["c"].mask.clone()
    mixed.mask[1, :7] = ~mixed.mask[1, :7]
    for run in (lambda: predict(HeightBands(mixed.grid.pos), mixed, up=torch.tensor([0.0, 0.0, 1.0]),
                                progress=False),
                lambda: split_up(net, mixed)):
        with pytest.raises(ValueError, match="different fields of view.*evaluate_fields"):
            run()
    assert split_up(net, copy.copy(sets["c"])).estimate.shape == (len(mixed), 3)


class RedBands(torch.nn.Module):
    """A planar "segmenter": class k where the red channel is in the k-th of 13 bands. It
    records the shape of every batch it reads."""

    input_dims = 4

    def __init__(self):
        super().__init__()
        self.shapes = []

    def forward(self, x, mask=None):
        self.shapes.append(tuple(x.shape))
        k = (x[:, 0] * 13).long().clamp(0, 12)
        return torch.nn.functional.one_hot(k, 13).permute(0, 3, 1, 2).float()


def test_a_planar_model_reads_other_lenses_as_a_panorama_and_its_labels_come_back(sets):
    """A panorama is read as it is; a fisheye's images are re-imaged as 2H x H panoramas,
    and the labels predicted there rendered back into its pixels (nearest): where the
    colour bands are wide, they are the bands of the fisheye's own pixels."""
    from scipy.ndimage import maximum_filter, minimum_filter

    from usf_graph.cameras import Equirectangular
    from usf_graph.frontend import render as reimage
    from usf_graph.frontend.interpolation import valid_pixels

    for name in ("b", "c"):
        ds, model = copy.copy(sets[name]), RedBands()
        rays, ok = ds.camera.lens_normal_map()  # red: the height of each pixel's ray, in 4 steps
        step = np.nan_to_num(np.floor((rays[..., 2] + 1) * 2)).clip(0, 3)
        red = np.round((3 * step + 1.5) / 13 * 255)  # the middle of bands 1, 4, 7 and 10
        ds.image = torch.as_tensor(np.repeat(red[None, ..., None], 3, -1), dtype=torch.uint8).repeat(3, 1, 1, 1)
        pix, points = predict(model, ds, batch_size=2, progress=False)
        S, H, W = ds.image.shape[:3]
        assert points is None and pix.shape == (S, H, W) and pix.dtype == np.uint8
        read = (H, 2 * H) if name == "c" else (H, W)
        assert model.shapes == [(2, 3, *read), (S - 2, 3, *read)]
        want = (ds.image[..., 0].numpy().astype(float) / 255 * 13).astype(int).clip(0, 12)
        # pixels whose 3 x 3 neighbourhood (in the image circle) is one band
        inside = np.where(valid_pixels(ds.camera), want, -1)
        wide = ((minimum_filter(inside, (1, 3, 3), mode="constant", cval=-1) == want)
                & (maximum_filter(inside, (1, 3, 3), mode="constant", cval=-1) == want))
        agree = (pix == want)[wide].mean()
        assert len(np.unique(want[wide])) == 4 and wide.sum() > 150
        assert agree == 1.0 if name == "b" else agree > 0.95  # the fisheye's: 1.0
    # back in the fisheye (the last), each pixel has the label of the panorama's pixel nearest its ray
    pano = Equirectangular(2 * H, H)
    x = torch.as_tensor(np.stack([reimage(im, ds.camera, pano) for im in ds.image.numpy()]))
    labels = model(x.permute(0, 3, 1, 2).float() / 255).argmax(1).numpy()
    uv, _ = pano.project(rays[ok])
    u, v = np.round(uv[:, 0]).astype(int) % (2 * H), np.round(uv[:, 1]).astype(int).clip(0, H - 1)
    assert np.array_equal(pix[:, ok], labels[:, v, u])


class FixedLogits(torch.nn.Module):
    """The same random logits ``[N, 13]`` for every view; it records the masks it is given."""

    def __init__(self, n):
        super().__init__()
        self.register_buffer("logits", 3 * torch.randn(n, 13, generator=torch.Generator().manual_seed(0)))
        self.masks = []

    def forward(self, x, mask=None, up=None):
        self.masks.append(mask)
        return self.logits.expand(len(x), -1, -1).to(x.dtype)


def test_predict_hands_the_field_of_view_on_and_renders_soft_from_probabilities(sets):
    fisheye, pano = sets["c"], sets["b"]
    model = FixedLogits(len(fisheye.grid.pos))
    predict(model, fisheye, batch_size=2, progress=False)
    assert len(model.masks) == 2 and all(torch.equal(m, fisheye.mask[0]) for m in model.masks)
    model.masks.clear()
    predict(model, pano, progress=False)
    assert model.masks == [None]  # a panorama sees everything: no mask to apply
    pix, _ = predict(model, fisheye, render="soft", progress=False)
    want = fisheye.frontend.to_labels(model.logits.softmax(-1), "soft").numpy()
    assert np.array_equal(pix[0], want) and np.array_equal(pix[2], want)
    nearest = predict(model, fisheye, progress=False)[0]
    assert np.array_equal(nearest[1], fisheye.frontend.to_labels(model.logits, "nearest").numpy())
    assert not np.array_equal(nearest[1], want)  # the two renderings differ here
    # blending the raw logits instead of the probabilities gives other labels
    assert not np.array_equal(fisheye.frontend.to_labels(model.logits, "soft").numpy(), want)
