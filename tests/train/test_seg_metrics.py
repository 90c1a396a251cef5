"""Segmentation metrics against hand-computed confusion matrices."""

import numpy as np
import pytest
import torch

from usf_graph.train.seg_metrics import (
    confusion_matrix,
    median_frequency_weights,
    per_image_miou,
    score,
    scores,
)


def test_confusion_and_scores_by_hand():
    # 3 classes; 255 ignored; class 2 never in the truth but predicted once
    target = np.array([[0, 0, 0, 1], [1, 1, 255, 0]])
    pred = np.array([[0, 0, 1, 1], [1, 2, 2, 0]])
    conf = confusion_matrix(pred, target, 3)
    want = np.array([[3, 1, 0],   # truth 0: predicted 0, 0, 1, 0
                     [0, 2, 1],   # truth 1: predicted 1, 1, 2
                     [0, 0, 0]], float)
    np.testing.assert_array_equal(conf, want)
    s = scores(conf, ["a", "b", "c"])
    # IoU_0 = 3 / (4 + 3 - 3) = 3/4; IoU_1 = 2 / (3 + 3 - 2) = 1/2; IoU_2 = 0 / (0 + 1 - 0) = 0
    assert s["IoU"] == {"a": 0.75, "b": 0.5, "c": 0.0}
    assert s["mIoU"] == pytest.approx((0.75 + 0.5 + 0.0) / 3)
    # accuracy over the classes in the truth only: 3/4 and 2/3
    assert s["Acc"] == {"a": 0.75, "b": pytest.approx(2 / 3), "c": None}
    assert s["mAcc"] == pytest.approx((0.75 + 2 / 3) / 2)
    assert s["acc"] == pytest.approx(5 / 7)


def test_weighted_confusion_and_absent_classes():
    target, pred = np.array([0, 1, 1]), np.array([0, 1, 0])
    conf = confusion_matrix(pred, target, 4, weight=np.array([0.5, 2.0, 1.0]))
    np.testing.assert_array_equal(conf[:2, :2], [[0.5, 0], [1.0, 2.0]])
    s = scores(conf)
    assert s["IoU"]["2"] is None and s["IoU"]["3"] is None  # neither true nor predicted
    assert s["mIoU"] == pytest.approx((0.5 / 1.5 + 2 / 3) / 2)
    with pytest.raises(ValueError, match="class indices"):
        confusion_matrix(np.array([7]), np.array([0]), 4)
    with pytest.raises(ValueError, match="differ in size"):
        confusion_matrix(np.zeros(3), np.zeros(4), 4)
    for bad in (np.nan, -1.0):
        with pytest.raises(ValueError, match="finite and >= 0"):
            confusion_matrix(pred, target, 4, weight=np.array([0.5, bad, 1.0]))


def test_the_edges_of_the_class_range():
    """Targets just outside [0, C) are not classes (left out); predictions there are refused;
    a zero area counts nothing; a class given as ``ignore_index`` is left out."""
    target, pred = np.array([-1, 0, 1, 2, 3]), np.array([1, 0, 1, 2, 0])
    np.testing.assert_array_equal(confusion_matrix(pred, target, 3), np.diag([1.0, 1, 1]))
    np.testing.assert_array_equal(confusion_matrix(pred, target, 3, ignore_index=1),
                                  np.diag([1.0, 0, 1]))
    for bad in (3, -1):
        with pytest.raises(ValueError, match="class indices"):
            confusion_matrix(np.array([0, bad]), np.array([0, 2]), 3)
    conf = confusion_matrix(pred, target, 3, weight=np.array([1.0, 0.0, 2.0, 0.5, 1.0]))
    np.testing.assert_array_equal(conf, np.diag([0.0, 2.0, 0.5]))


def test_per_image_mean_differs_from_dataset_level():
    a = confusion_matrix(np.array([0, 0]), np.array([0, 0]), 2)  # image 1: perfect, class 0 only
    b = confusion_matrix(np.array([0, 1, 1, 1]), np.array([1, 1, 1, 1]), 2)  # image 2
    assert per_image_miou([a, b]) == pytest.approx((1.0 + (0 + 0.75) / 2) / 2)
    assert scores(a + b)["mIoU"] == pytest.approx((2 / 3 + 0.75) / 2)


def test_median_frequency_weights():
    w = median_frequency_weights([10, 30, 0, 20])
    assert torch.allclose(w, torch.tensor([2.0, 2 / 3, 0.0, 1.0]))
    with pytest.raises(ValueError, match="positive total"):
        median_frequency_weights([0, 0])
    # areas as well as counts, a class seen once, and an even number of classes seen
    assert torch.allclose(median_frequency_weights([0.2, 0.6, 0.0, 0.4]), torch.tensor([2.0, 2 / 3, 0.0, 1.0]))
    assert torch.allclose(median_frequency_weights([1, 3, 2]), torch.tensor([2.0, 2 / 3, 1.0]))
    assert torch.allclose(median_frequency_weights([10, 20, 0, 30, 40]),
                          torch.tensor([2.5, 1.25, 0.0, 25 / 30, 0.625]))
    for bad in ([3, -1], [3, float("nan")], [3, float("inf")]):
        with pytest.raises(ValueError, match="finite and >= 0"):
            median_frequency_weights(bad)


def test_scores_of_small_areas_and_the_default_ignore_index():
    """Areas on the sphere are fractions of 4 pi: a class whose area sums under 1 still has
    an accuracy; 255 is left out by default even where it would be a class."""
    conf = confusion_matrix(np.array([0, 1, 1, 0]), np.array([0, 1, 0, 0]), 2, weight=np.full(4, 0.01))
    s = scores(conf)
    assert s["Acc"] == {"0": pytest.approx(2 / 3), "1": pytest.approx(1.0)}
    assert s["mAcc"] == pytest.approx(5 / 6) and s["mIoU"] == pytest.approx((2 / 3 + 1 / 2) / 2)
    conf = confusion_matrix(np.array([3, 255, 255]), np.array([3, 255, 3]), 300)
    assert conf.sum() == 2 and conf[3, 3] == 1 and conf[3, 255] == 1


def test_score_on_pixels_and_area_weighted_on_the_grid():
    """``score`` of a dataset's pixels and grid points: the pixel metrics summed over images,
    the sphere's weighted by each point's area."""
    from types import SimpleNamespace

    from usf_graph.scenes import SEMANTIC_CLASSES

    C = len(SEMANTIC_CLASSES)
    truth = torch.tensor([[[0, 1], [1, 255]], [[2, 2], [0, 1]]])
    pred = np.array([[[0, 1], [0, 0]], [[2, 1], [0, 1]]])
    y = torch.tensor([[0, 1, 2], [2, 2, 255]])
    area = torch.tensor([1.0, 3.0, 0.5], dtype=torch.float64)
    ds = SimpleNamespace(label_image=truth, y=y, grid=SimpleNamespace(area=area))
    points = np.array([[0, 2, 2], [1, 2, 0]])
    res = score(pred, ds, points)
    want = scores(confusion_matrix(pred, truth.numpy(), C), SEMANTIC_CLASSES)
    assert res["mIoU"] == pytest.approx(want["mIoU"]) and res["mAcc"] == pytest.approx(want["mAcc"])
    # the grid, (truth, prediction) with the point's area: image 0 (0, 0) 1, (1, 2) 3,
    # (2, 2) 0.5; image 1 (2, 1) 1, (2, 2) 3, its third point ignored
    assert res["sphere_mIoU"] == pytest.approx((1 + 0 + 3.5 / (4.5 + 6.5 - 3.5)) / 3)
    assert "sphere_mIoU" not in score(pred, ds)
