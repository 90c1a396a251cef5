import json

import cv2
import numpy as np
import pytest

from usf_graph import cameras, scenes
from usf_graph.ops import from_pandora
from usf_graph.scenes.export import depth_png, pandora_json, save_view


def test_files_are_in_the_real_formats(tmp_path):
    cam = cameras.Equirectangular(256, 128)
    view = scenes.render(scenes.make_room(0, 4), cam)
    files = save_view(view, tmp_path, "v")
    lab = cv2.imread(str(tmp_path / files["label"]), cv2.IMREAD_UNCHANGED)
    assert lab.dtype == np.uint8 and np.array_equal(lab, view.label)
    depth = cv2.imread(str(tmp_path / files["depth"]), cv2.IMREAD_UNCHANGED)
    assert depth.dtype == np.uint16
    np.testing.assert_allclose(depth / 512, view.depth, atol=1 / 1024)  # Stanford: 1/512 m
    rgb = cv2.imread(str(tmp_path / files["rgb"]))[..., ::-1]
    assert np.array_equal(rgb, view.rgb)
    doc = json.loads(json.dumps(pandora_json([("v_rgb.png", view)], cam)))
    got = np.array([a["bbox"] for a in doc["annotations"]])
    np.testing.assert_allclose(from_pandora(got), view.boxes, atol=1e-6)
    ids = [a["category_id"] for a in doc["annotations"]]
    names = {c["id"]: c["name"] for c in doc["categories"]}
    assert [names[i] for i in ids] == [scenes.DETECTION_CLASSES[c] for c in view.box_class]
    assert len(doc["categories"]) == 47 and names[46] == "window"


def test_missing_depth_is_65535_and_fisheye_boxes_are_refused():
    d = depth_png(np.array([[1.0, 2.0]]), np.array([[True, False]]))
    assert d.tolist() == [[512, 65535]]
    fish = cameras.Fisheye(100, 99.5, 99.5, 200, 200)
    with pytest.raises(ValueError, match="equirectangular"):
        pandora_json([], fish)
