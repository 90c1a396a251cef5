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
