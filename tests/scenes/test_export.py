import json

import cv2
import numpy as np
import pytest

from usf_graph import cameras, grids, scenes
from usf_graph.frontend import SphericalFrontend
from usf_graph.ops import from_pandora
from usf_graph.scenes.export import (
    depth_png,
    export_pandora,
    export_stanford,
    pandora_json,
    save_view,
    stanford_semantic,
)


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
    # COCO's bookkeeping: ids 1..K, every box its image's, none a crowd, no "-0.0"
    anns = doc["annotations"]
    assert [a["id"] for a in anns] == list(range(1, len(anns) + 1)) and len(anns) > 2
    assert doc["images"] == [{"id": 1, "file_name": "v_rgb.png", "width": cam.width, "height": cam.height}]
    assert all(a["image_id"] == 1 and a["iscrowd"] == 0 for a in anns)
    assert "-0.0," not in json.dumps(doc) and "-0.0]" not in json.dumps(doc)


def test_stanford_semantic_pixels_index_the_label_list_and_missing_ones_are_0x0d0d0d():
    got = stanford_semantic(np.array([[255, 0, 12]], np.uint8))
    assert got.tolist() == [[[13, 13, 13], [0, 0, 1], [0, 0, 13]]] and got.dtype == np.uint8


def test_missing_depth_is_65535_and_fisheye_boxes_are_refused():
    d = depth_png(np.array([[1.0, 2.0]]), np.array([[True, False]]))
    assert d.tolist() == [[512, 65535]]
    fish = cameras.Fisheye(100, 99.5, 99.5, 200, 200)
    with pytest.raises(ValueError, match="equirectangular"):
        pandora_json([], fish)


def test_rooms_as_stanford_and_pandora_releases_read_back_through_the_real_loaders(tmp_path):
    """`usf-graph scenes --layout stanford2d3ds|pandora` writes rooms in the releases' layouts;
    the real datasets' loaders read back the rendered labels, images and boxes."""
    from usf_graph.cli import main
    from usf_graph.datasets import Pandora, Stanford2D3DS
    from usf_graph.datasets.stanford import FOLDS

    cam = cameras.Equirectangular(64, 32)
    views = [scenes.render(scenes.make_room(0, i), cam) for i in range(7)]
    assert main(["scenes", "--out", str(tmp_path / "s"), "--num", "7", "--size", "32",
                 "--layout", "stanford2d3ds"]) == 0
    for fold in (1, 3):
        test = Stanford2D3DS(tmp_path / "s", fold, "test", grid="icosahedral:2", size=32, progress=False)
        rooms = [i for i in range(7) if ("1", "2", "3", "4", "5a", "5b", "6")[i] in FOLDS[fold][1]]
        assert test.names == [f"camera_{i:06d}_procedural_{i}" for i in rooms]
        for k, i in enumerate(rooms):  # the same size: nothing resized, so exactly the views
            assert np.array_equal(test.label_image[k].numpy(), views[i].label)
            assert np.array_equal(test.image[k].numpy(), views[i].rgb)
    assert (views[0].label == scenes.IGNORE).sum() == 0  # a panorama: every pixel a class
    assert main(["scenes", "--out", str(tmp_path / "p"), "--num", "7", "--size", "32",
                 "--layout", "pandora"]) == 0
    for split, rooms in (("train", [0, 1, 2, 3, 5, 6]), ("test", [4])):
        ds = Pandora(tmp_path / "p", split, grid="icosahedral:2", progress=False)
        assert len(ds) == len(rooms)
        for k, i in enumerate(rooms):
            d = ds[k]
            np.testing.assert_allclose(d.boxes.numpy(), views[i].boxes, atol=1e-6)
            want = [scenes.PANDORA_CLASSES.index(scenes.DETECTION_CLASSES[c]) for c in views[i].box_class]
            assert d.box_class.tolist() == want
            # the JPEG holds the view's colours, in RGB order once read back
            rgb = SphericalFrontend(cam, grids.icosahedral(2), "area").lift(views[i].rgb / 255.0)
            assert float((d.x.double() - rgb).abs().mean()) < 0.02
    with pytest.raises(ValueError, match="equirectangular"):
        export_stanford(views[:1], cameras.Fisheye(100, 99.5, 99.5, 200, 200), tmp_path / "x")
    with pytest.raises(ValueError, match="test_every"):
        export_pandora(views[:1], cam, tmp_path / "x", test_every=1)
