"""DetectionSet: batches, first samples and the true boxes a camera sees, on splits built
here (three samples holding two, none and one box)."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from usf_graph.cameras import Equirectangular, Pinhole
from usf_graph.ops.boxes import from_pandora
from usf_graph.train.det_data import DetectionSet, boxes_seen
from usf_graph.train.det_metrics import FULLY_SEEN

# PANDORA degrees: ahead of a 90-degree pinhole, across its right edge, behind it
BOXES = torch.as_tensor(from_pandora(np.array([[0, 0, 20, 20, 0], [45, 0, 20, 20, 0],
                                               [180, 0, 20, 20, 0]], np.float64)))
PTR, CLASSES = torch.tensor([0, 2, 2, 3]), torch.tensor([4, 1, 7])
PINHOLE = Pinhole(8, 8, 7.5, 7.5, 16, 16)  # 90 degrees, looking along +x


def _split(mask=None, camera=PINHOLE, n_points=12):
    x = torch.arange(3 * n_points * 2, dtype=torch.float64).reshape(3, n_points, 2)
    return SimpleNamespace(x=x, mask=mask, boxes=BOXES, box_class=CLASSES, box_ptr=PTR, camera=camera,
                           image=torch.randint(0, 256, (3, 16, 16, 3), dtype=torch.uint8,
                                               generator=torch.Generator().manual_seed(0)))


def test_collate_gathers_each_samples_boxes_in_batch_order():
    ds = DetectionSet.spherical(_split())
    x, mask, boxes, classes, image = ds.collate([2, 1, 0])
    assert x.dtype == torch.float32 and torch.equal(x, ds.x[[2, 1, 0]].float()) and mask is None
    assert torch.equal(boxes, BOXES[[2, 0, 1]].float()) and classes.tolist() == [7, 4, 1]
    assert image.tolist() == [0, 2, 2]  # sample 1 has no box
    assert [len(t) for t in ds.collate([1])[2:]] == [0, 0, 0] and len(ds.collate([])[2]) == 0
    assert ds.truth(0)[1].tolist() == [4, 1] and len(ds.truth(1)[0]) == 0 and len(ds) == 3
    # uint8 images become [B, 3, H, W] in [0, 1]
    img = DetectionSet(_split().image, BOXES, CLASSES, PTR)
    x = img.collate([1])[0]
    assert x.shape == (1, 3, 16, 16) and torch.equal(x[0, 2], img.x[1, :, :, 2].float() / 255)


def test_the_boxes_a_camera_sees_too_little_of_are_ignored():
    mask = torch.ones(12, dtype=torch.bool)
    mask[:3] = False
    ds = DetectionSet.spherical(_split(mask.expand(3, 12)))  # one field of view, per sample
    assert torch.equal(ds.mask, mask)
    assert ds.seen[0] == pytest.approx(1.0) and 0.3 < ds.seen[1] < 0.7 and ds.seen[2] == 0.0
    assert ds.ignored().tolist() == [False, True, True]
    assert ds.ignored(0).tolist() == [False, True] and ds.ignored(1).tolist() == []
    assert ds.describe_ignored() == (f"3 true boxes, 2 of them ignored (the camera sees less than "
                                     f"{FULLY_SEEN:.0%} of them)")
    # everything seen: no mask and nothing ignored, with or without a camera
    whole = DetectionSet.spherical(_split(torch.ones(12, dtype=torch.bool), camera=None))
    assert whole.mask is None and whole.seen is None and not whole.ignored().any()
    with pytest.raises(ValueError, match="different fields of view"):
        DetectionSet.spherical(_split(torch.stack([mask, ~mask, mask])))
    with pytest.raises(ValueError, match="no camera to tell which share of each box"):
        DetectionSet.spherical(_split(mask, camera=None))
    assert np.array_equal(boxes_seen(_split()), ds.seen)


def test_first_samples_keep_their_boxes_and_what_is_seen():
    mask = torch.arange(12) > 2
    ds = DetectionSet.spherical(_split(mask))
    two = ds.first(2)
    assert len(two) == 2 and torch.equal(two.x, ds.x[:2]) and torch.equal(two.boxes, ds.boxes[:2])
    assert two.box_ptr.tolist() == [0, 2, 2] and two.box_class.tolist() == [4, 1]
    assert two.seen.tolist() == ds.seen[:2].tolist() and torch.equal(two.mask, mask)
    assert len(ds.first(10)) == 3 and len(ds.first(10).boxes) == 3
    assert DetectionSet(ds.x, BOXES, CLASSES, PTR).first(1).seen is None


def test_planar_splits_are_panoramas():
    """The planar detector reads panoramas: a panorama split as it is, another camera's
    images re-imaged, with the part of the panorama that camera sees as the mask."""
    pano = Equirectangular(32, 16)
    split = _split(camera=pano)
    split.image = torch.zeros(3, 16, 32, 3, dtype=torch.uint8)
    same = DetectionSet.planar(split, 32, 16)
    assert same.x is split.image and same.mask is None and same.seen is None
    ds = DetectionSet.planar(_split(), 32, 16, progress=False)
    assert ds.x.shape == (3, 16, 32, 3) and ds.x.dtype == torch.uint8
    _, seen = PINHOLE.sees(pano.lens_normal_map()[0].reshape(-1, 3))
    assert torch.equal(ds.mask, torch.as_tensor(seen.reshape(16, 32))) and 0 < ds.mask.float().mean() < 0.3
    assert ds.ignored().tolist() == [False, True, True]
    assert (ds.x[:, ~ds.mask] == 0).all() and ds.x[:, ds.mask].float().std() > 20


def test_inconsistent_splits_are_refused():
    x = torch.zeros(3, 12, 2)
    with pytest.raises(ValueError, match="box_ptr has 3 entries for 3 samples"):
        DetectionSet(x, BOXES, CLASSES, PTR[:3])
    with pytest.raises(ValueError, match="seen has 2 entries for 3 boxes"):
        DetectionSet(x, BOXES, CLASSES, PTR, seen=[1.0, 1.0])
