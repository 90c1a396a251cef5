import numpy as np
import pytest
import torch

from tests.helpers import random_sphere
from usf_graph.geometry import from_latlon
from usf_graph.ops import box_iou, from_pandora, points_in_boxes
from usf_graph.train.det_metrics import coco_ap, usf_map


def P(*rows):
    return from_pandora(np.array(rows, np.float64))


GT = [(P([0, 0, 20, 20, 0], [179, 10, 30, 20, 45]), np.array([0, 1])),
      (P([0, 85, 30, 30, 0]), np.array([1]))]


def test_perfect_detections_score_one():
    dets = [(b, c, np.ones(len(c))) for b, c in GT]
    assert coco_ap(GT, dets, 2) == pytest.approx({"AP": 1.0, "AP50": 1.0, "AP75": 1.0,
                                                          "AR50": 1.0})


def test_ap_thresholds_follow_the_spherical_iou():
    # shifted by 4 degrees: IoU 0.67 for the 20x20 box, so it counts at 0.50 and not at 0.75
    shifted = P([4, 0, 20, 20, 0])
    assert 0.6 < float(box_iou(shifted, GT[0][0][0])) < 0.7
    truth = [(GT[0][0][:1], np.array([0]))]
    r = coco_ap(truth, [(shifted, np.array([0]), np.array([0.9]))], 1)
    assert r["AP50"] == pytest.approx(1.0) and r["AP75"] == pytest.approx(0.0)
    # AP averages the ten thresholds 0.50:0.95; IoU 0.67 passes 0.50, 0.55, 0.60, 0.65
    assert r["AP"] == pytest.approx(0.4)


def test_ar50_counts_found_boxes_whatever_their_rank():
    # class 0: two true boxes, one found (ranked below a false box); class 1: its box missed
    truth = [(P([0, 0, 20, 20, 0], [90, 0, 20, 20, 0], [179, 10, 30, 20, 45]), np.array([0, 0, 1]))]
    dets = [(P([0, 0, 20, 20, 0], [-90, 0, 20, 20, 0]), np.array([0, 0]), np.array([0.5, 0.9]))]
    r = coco_ap(truth, dets, 2)
    assert r["AR50"] == pytest.approx((0.5 + 0.0) / 2)
    # AP50: class 0 reaches precision 1/2 at recall 1/2 (101-point interpolation), class 1 none
    assert r["AP50"] == pytest.approx((51 * 0.5 / 101 + 0.0) / 2)


def test_seam_and_pole_matches_count_and_wrong_classes_do_not():
    # PANDORA can write the same box with lon 179 or -181 and a box over the pole in any lon
    same = P([-181, 10, 30, 20, 45], [0, 85, 30, 30, 0])
    r = coco_ap([(GT[0][0][1:], [1]), GT[1]], [(same[:1], [1], [0.8]), (same[1:], [1], [0.7])], 2)
    assert r["AP50"] == pytest.approx(1.0)
    wrong = coco_ap(GT, [(b, 1 - c if len(c) == 2 else c * 0, np.ones(len(c))) for b, c in GT], 2)
    assert wrong["AP50"] == pytest.approx(0.0) and wrong["AR50"] == pytest.approx(0.0)


def test_no_detections_and_mismatched_lengths():
    assert coco_ap(GT, [(np.zeros((0, 5)), [], []), (np.zeros((0, 5)), [], [])], 2)["AP"] == 0.0
    with pytest.raises(ValueError, match="2 images"):
        coco_ap(GT, [], 2)


@pytest.mark.parametrize("metric", [coco_ap, usf_map])
def test_bad_classes_scores_and_lengths_are_refused(metric):
    box = P([0, 0, 20, 20, 0])
    truth = [(box, np.array([0]))]
    with pytest.raises(ValueError, match="NaN"):  # pycocotools scored it a hit
        metric(truth, [(box, np.array([0]), np.array([np.nan]))], 2)
    with pytest.raises(ValueError, match=r"0 \.\. 1, got \[5\]"):  # pycocotools: AP -1
        metric([(box, np.array([5]))], [(box, np.array([0]), np.array([0.9]))], 2)
    with pytest.raises(ValueError, match="0 .. 1"):
        metric(truth, [(box, np.array([-1]), np.array([0.9]))], 2)
    with pytest.raises(ValueError, match="1 detected boxes but 1 classes and 2 scores"):
        metric(truth, [(box, np.array([0]), np.array([0.9, 0.8]))], 2)
    with pytest.raises(ValueError, match="2 images"):
        metric(GT, [], 2)


def test_usf_map_per_image_and_class_with_end_points():
    perfect = [(b, c, np.ones(len(c))) for b, c in GT]
    assert usf_map(GT, perfect, 2) == pytest.approx(1.0)
    # image 0 class 0: a false positive ranked above the hit -> precision 1/2 at recall 1
    far = P([90, 0, 20, 20, 0])
    dets = [(np.concatenate([far, GT[0][0]]), np.array([0, 0, 1]), np.array([0.9, 0.8, 0.7])),
            (GT[1][0], GT[1][1], np.ones(1))]
    assert usf_map(GT, dets, 2) == pytest.approx((0.5 + 1 + 1) / 3)
    # a box shifted to IoU ~0.33 counts at IoU 0.10 and not at 0.50
    half = P([10, 0, 20, 20, 0])
    one = [(GT[0][0][:1], np.array([0]))]
    assert usf_map(one, [(half, np.array([0]), np.ones(1))], 1, 0.10) == pytest.approx(1.0)
    assert usf_map(one, [(half, np.array([0]), np.ones(1))], 1, 0.50) == pytest.approx(0.0)
    # no detections at all: AP 0 for every (image, class) with ground truth
    empty = [(np.zeros((0, 5)), np.zeros(0, int), np.zeros(0)) for _ in GT]
    assert usf_map(GT, empty, 2) == 0.0


def test_ignored_boxes_are_neither_hits_nor_misses():
    # image 0: box A (class 0) found exactly; box B (class 0) cut by the camera, ignored
    A, B = P([0, 0, 20, 20, 0]), P([60, 0, 40, 30, 0])
    truth = [(np.concatenate([A, B]), np.array([0, 0]))]
    ig = [np.array([False, True])]
    found_a = [(A, np.array([0]), np.array([0.5]))]
    assert coco_ap(truth, found_a, 1, ig)["AP50"] == pytest.approx(1.0)  # B is not missed
    assert coco_ap(truth, found_a, 1)["AP50"] == pytest.approx(51 / 101)  # counted: recall 1/2
    # a detection of the part of B the camera sees (inside B, IoU with B under 0.5), ranked
    # first: matched to the ignored box, so no false positive
    part = P([50, 0, 20, 20, 0])
    assert float(box_iou(part, B)) < 0.5 and points_in_boxes(from_latlon(0.0, np.radians(-50)), B)[0, 0]
    both = [(np.concatenate([part, A]), np.array([0, 0]), np.array([0.9, 0.5]))]
    assert coco_ap(truth, both, 1, ig)["AP50"] == pytest.approx(1.0)
    # without the flag it is a false positive ranked above the hit
    assert coco_ap(truth, both, 1)["AP50"] == pytest.approx(51 * 0.5 / 101)
    # a detection elsewhere still is one, and an ignored box never counts as a hit
    far = P([-90, 0, 20, 20, 0])
    r = coco_ap(truth, [(np.concatenate([far, A]), np.array([0, 0]), np.array([0.9, 0.5]))], 1, ig)
    assert r["AP50"] == pytest.approx(0.5)  # precision 1/2 up to recall 1
    only_b = coco_ap(truth, [(B, np.array([0]), np.array([0.9]))], 1, ig)
    assert only_b["AP50"] == pytest.approx(0.0) and only_b["AR50"] == pytest.approx(0.0)
    with pytest.raises(ValueError, match="2 true boxes but 1"):
        coco_ap(truth, found_a, 1, [np.array([True])])


def test_ar50_is_read_at_iou_050():
    # IoU 0.52: found at 0.50, not at 0.55, the next threshold COCO's recall table holds
    near = P([6.3, 0, 20, 20, 0])
    assert 0.5 < float(box_iou(near, GT[0][0][0])) < 0.55
    r = coco_ap([(GT[0][0][:1], np.array([0]))], [(near, np.array([0]), np.array([0.9]))], 1)
    assert r["AR50"] == pytest.approx(1.0) and r["AP"] == pytest.approx(0.1)


def test_usf_map_matches_each_true_box_once_and_takes_the_envelope():
    box = GT[0][0][:1]
    one = [(box, np.array([0]))]
    # the same box detected twice: the second is a false positive -> AP 1 (not recall 2)
    twice = [(np.concatenate([box, box]), np.array([0, 0]), np.array([0.9, 0.8]))]
    assert usf_map(one, twice, 1) == pytest.approx(1.0)
    # two true boxes; hit, miss, hit: precision 1, 1/2, 2/3 at recall 1/2, 1/2, 1, so the
    # envelope is 1 up to recall 1/2 and 2/3 after: AP = 1/2 + 1/3
    two = [(np.concatenate([box, P([90, 0, 20, 20, 0])]), np.array([0, 0]))]
    dets = [(np.concatenate([box, P([-90, 0, 20, 20, 0]), P([90, 0, 20, 20, 0])]),
             np.array([0, 0, 0]), np.array([0.9, 0.8, 0.7]))]
    assert usf_map(two, dets, 1) == pytest.approx(0.5 + 1 / 3)


def test_ar50_takes_the_hundred_best_and_only_classes_with_truth():
    """The one hit ranked twelfth among its class's detections in the image still counts
    (pycocotools keeps 100 a image, not 10); a class with no true box is not averaged in."""
    box = P([0, 0, 20, 20, 0])
    far = P(*[[-150 + 20 * k, 0, 10, 10, 0] for k in range(11)])
    dets = [(np.concatenate([far, box]), np.zeros(12, int), np.r_[np.linspace(0.9, 0.8, 11), 0.1])]
    r = coco_ap([(box, np.array([0]))], dets, 3)
    assert r["AR50"] == pytest.approx(1.0) and r["AP50"] == pytest.approx(1 / 12, abs=0.01)


def test_a_detection_counts_against_a_crowd_box_by_its_share_inside():
    """Against an ignored box the overlap is the share of the detection inside it (checked
    here by sampling directions): 0.60 inside matches it; 0.46 does not, and is a false
    positive ranked above the hit."""
    A, crowd = P([-90, 0, 20, 20, 0]), P([0, 0, 40, 40, 0])
    truth, ig = [(np.concatenate([A, crowd]), np.array([0, 0]))], [np.array([False, True])]
    dirs = random_sphere(1_000_000, 0, torch.float64).numpy()
    for lon, share, ap50 in ((-18.0, 0.60, 1.0), (-20.8, 0.46, 0.5)):  # PANDORA's lon runs the other way
        part = P([lon, 0, 20, 20, 0])
        inside = points_in_boxes(dirs, np.concatenate([part, crowd]))
        assert abs((inside[:, 0] & inside[:, 1]).sum() / inside[:, 0].sum() - share) < 0.015
        dets = [(np.concatenate([part, A]), np.array([0, 0]), np.array([0.9, 0.5]))]
        assert coco_ap(truth, dets, 1, ig)["AP50"] == pytest.approx(ap50)


def test_a_class_one_past_the_last_is_refused():
    box = P([0, 0, 20, 20, 0])
    with pytest.raises(ValueError, match=r"0 \.\. 1, got \[2\]"):
        coco_ap([(box, np.array([0]))], [(box, np.array([2]), np.array([0.9]))], 2)


def test_no_true_box_anywhere_reports_minus_one():
    """pycocotools' -1 for "nothing to score", for AR50 too (not a NaN mean of no classes)."""
    r = coco_ap([(np.zeros((0, 5)), np.zeros(0, int))], [(P([0, 0, 20, 20, 0]), [0], [0.9])], 2)
    assert r["AP"] == -1.0 and r["AR50"] == -1.0


def test_usf_map_threshold_is_inclusive():
    truth, near = GT[0][0][:1], P([6.3, 0, 20, 20, 0])
    iou = float(box_iou(near, truth[0]))
    dets = [(near, np.array([0]), np.array([0.9]))]
    assert usf_map([(truth, np.array([0]))], dets, 1, iou_threshold=iou) == pytest.approx(1.0)
    assert usf_map([(truth, np.array([0]))], dets, 1, iou_threshold=np.nextafter(iou, 1)) == 0.0
