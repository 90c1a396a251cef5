import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from usf_graph.datasets import Pandora, read_annotations
from usf_graph.geometry import from_latlon
from usf_graph.ops import points_in_boxes

FIX = Path(__file__).resolve().parents[1] / "fixtures" / "pandora"


@pytest.fixture()
def root(tmp_path):
    shutil.copytree(FIX, tmp_path / "pandora")
    return tmp_path / "pandora"


def test_reads_the_release_layout_and_converts_boxes(root):
    ds = Pandora(root, "train", grid="icosahedral:2", progress=False)
    assert len(ds) == 2
    d = ds[0]
    assert d.x.shape == (162, 3) and d.boxes.shape == (3, 5)
    assert d.box_class.tolist() == [10, 39, 23]  # chair, table, light (PANDORA ids 11, 40, 24)
    # across the seam: PANDORA lon 179 (right edge) is our lon -179
    assert math.degrees(float(d.boxes[0, 0])) == pytest.approx(-179.0, abs=1e-4)
    # gamma 90 turns a 20x20 box onto itself; the pole box contains the pole
    north = from_latlon(math.pi / 2, 0.0)
    assert points_in_boxes(north, d.boxes[2].double().numpy())[0, 0]
    test = Pandora(root, "test", grid="icosahedral:2", progress=False)
    assert len(test) == 2 and test[1].boxes.shape == (0, 5)
    # released upright: every panorama's known up is +z
    want = torch.tensor([[0.0, 0.0, 1.0]] * 2, dtype=torch.float64)
    assert torch.equal(ds.gravity, want) and ds.gravity.dtype == torch.float64


def test_roll_sign_matches_pandoras_definition(root):
    boxes, _ = read_annotations(root / "annotations" / "test.json")["0003.jpg"]
    # [0, 0, 60, 20, 30] contains (lon 22, lat 12) in PANDORA's terms, not (22, -12)
    inside, outside = from_latlon(math.radians(12), -math.radians(22)), from_latlon(-math.radians(12), -math.radians(22))
    assert points_in_boxes(inside, boxes)[0, 0] and not points_in_boxes(outside, boxes)[0, 0]


def test_lifted_pixels_are_the_image(root):
    import cv2

    ds = Pandora(root, "train", grid="icosahedral:3", interpolation="bilinear", progress=False)
    from usf_graph import SphericalFrontend, cameras

    img = cv2.imread(str(root / "images" / "0001.jpg"))[..., ::-1].astype(np.float32) / 255
    fe = SphericalFrontend(cameras.Equirectangular(64, 32), ds.grid)
    torch.testing.assert_close(ds[0].x, fe.lift(img), atol=2e-3, rtol=0)


def test_panoramas_of_other_sizes_lift_through_their_own_camera_and_others_are_refused(root):
    import cv2

    from usf_graph import SphericalFrontend, cameras

    ds = Pandora(root, "train", grid="icosahedral:3", progress=False)
    path = root / "images" / "0001.jpg"
    big = cv2.resize(cv2.imread(str(path)), (128, 64), interpolation=cv2.INTER_NEAREST)
    cv2.imwrite(str(path), big)
    shutil.rmtree(root / "processed")
    mixed = Pandora(root, "train", grid="icosahedral:3", progress=False)
    img = cv2.imread(str(path))[..., ::-1].astype(np.float32) / 255
    fe = SphericalFrontend(cameras.Equirectangular(128, 64), mixed.grid, interpolation="area")
    torch.testing.assert_close(mixed[0].x, fe.lift(img), atol=2e-3, rtol=0)
    torch.testing.assert_close(mixed[1].x, ds[1].x)  # the others as before
    cv2.imwrite(str(path), big[:, :96])
    shutil.rmtree(root / "processed")
    with pytest.raises(ValueError, match=r"0001.jpg is 96 x 64; PANDORA panoramas are equirectangular, "
                                         r"twice as wide as high"):
        Pandora(root, "train", grid="icosahedral:3", progress=False)


def test_missing_data_says_how_to_get_it(tmp_path, root):
    with pytest.raises(FileNotFoundError, match=r"annotations/train.json not found\. .*SphericalObjectDetection"):
        Pandora(tmp_path, "train", progress=False)
    with pytest.raises(ValueError, match="split must be 'train' or 'test', got 'val'"):
        Pandora(root, "val", progress=False)
    image = root / "images" / "0001.jpg"  # of the train split
    image.unlink()
    with pytest.raises(FileNotFoundError, match=rf"{image.name} is missing or not an image\. PANDORA is"):
        Pandora(root, "train", grid="icosahedral:1", progress=False)


def test_bad_annotations_are_named(root):
    path = root / "annotations" / "train.json"
    doc = json.loads(path.read_text())
    doc["annotations"][1]["category_id"] = 48
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="annotation 2 of train.json has category_id 48"):
        Pandora(root, "train", grid="icosahedral:2", progress=False)
    doc["annotations"][1]["category_id"] = 40
    doc["annotations"][0]["bbox"] = [1, 2, 3]
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="5 finite numbers"):
        read_annotations(path)
    for bad in ([0, 95, 20, 20, 0], [0, 90.5, 20, 20, 0], [0, -90.5, 20, 20, 0], [0, 0, 0, 20, 0],
                [0, 0, 180, 20, 0], [0, 0, -5, 20, 0], [0, 0, 20, 0, 0], [0, 0, 20, 180, 0]):
        doc["annotations"][0]["bbox"] = bad
        path.write_text(json.dumps(doc))
        with pytest.raises(ValueError, match=r"annotation 1 of train.json .* fields of view in \(0, 180\)"):
            read_annotations(path)
    # boxes on the poles (lat 90 and -90) are valid, and any field of view short of 0 and 180
    for good in ([10, 90, 20, 20, 0], [10, -90, 20, 20, 0], [0, 0, 0.5, 179.5, 0], [0, 0, 179.5, 0.5, 0]):
        doc["annotations"][0]["bbox"] = good
        path.write_text(json.dumps(doc))
        assert len(read_annotations(path)) == len(doc["images"])
    for cat, ok in ((0, False), (1, True), (47, True), (48, False), (2.0, False)):
        doc["annotations"][0]["category_id"] = cat
        path.write_text(json.dumps(doc))
        if ok:
            _, classes = read_annotations(path)[doc["images"][0]["file_name"]]
            assert classes[0] == cat - 1  # PANDORA's 1..47 are our 0..46
        else:
            with pytest.raises(ValueError, match=f"has category_id {cat}; PANDORA's are 1..47"):
                read_annotations(path)
    doc["annotations"][0]["category_id"] = 1
    doc["annotations"][0]["image_id"] = 99
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="annotation 1 of train.json refers to image 99, which is not listed"):
        read_annotations(path)
    path.write_text("{not json")
    with pytest.raises(ValueError, match="not a PANDORA annotation file"):
        read_annotations(path)


def test_lifting_shows_a_progress_bar_unless_told_not_to(root, capsys):
    Pandora(root, "test", grid="icosahedral:1")
    assert "lifting PANDORA test" in capsys.readouterr().err
    Pandora(root, "train", grid="icosahedral:1", progress=False)
    assert capsys.readouterr().err == ""
