"""What every calibration reader shares (``cameras/files.py``): values checked by name, and
a file read by its content into one dict, without running anything it holds."""

from pathlib import Path

import numpy as np
import pytest

from tests.helpers import CodeOnLoad
from usf_graph.cameras.files import Src, read_document

SRC = Src(Path("calib.yaml"), "cam0")


def test_missing_keys_say_what_to_do():
    with pytest.raises(ValueError, match=r"calib.yaml \[cam0\]: missing key 'fx' in 'intrinsics'; "
                                         r"the calibration file is incomplete$"):
        SRC.need({}, "fx", "intrinsics")
    with pytest.raises(ValueError, match=r"missing key 'fx'; give the focal length$"):
        SRC.need({"fx": None}, "fx", hint="give the focal length")


def test_image_sizes_are_whole_positive_pixels():
    assert SRC.pixels([1, 480], "resolution") == (1, 480)
    for bad in ([0, 480], [752.7, 480], [float("nan"), 480]):
        with pytest.raises(ValueError, match="'resolution' must be whole positive numbers of pixels"):
            SRC.pixels(bad, "resolution")


def test_arrays_must_hold_numbers_and_transforms_take_12_or_16():
    with pytest.raises(ValueError, match=r"'D' must hold numbers, got \['a', 'b'\]"):
        SRC.array(["a", "b"], "D")
    T = np.hstack([np.eye(3), [[1.0], [2.0], [3.0]]])
    for given in (T.ravel(), np.vstack([T, [0, 0, 0, 1]]).ravel()):
        np.testing.assert_array_equal(SRC.rigid(given.tolist(), "T_cam_imu")[:3], T)
    with pytest.raises(ValueError, match="'T_cam_imu' must have 12 or 16 elements, got 9"):
        SRC.rigid(np.eye(3).ravel().tolist(), "T_cam_imu")


def test_an_npz_holding_pickled_objects_is_refused_without_running_them(tmp_path):
    path = tmp_path / "kd.npz"
    mark = tmp_path / "ran"
    np.savez(path, K=np.eye(3), D=np.array([CodeOnLoad(mark)], dtype=object))
    with pytest.raises(ValueError, match=f"cannot read {path}"):
        read_document(path, None)
    assert not mark.exists()


@pytest.mark.parametrize("name, text", [
    ("camera.yml", "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\nmodel: pinhole\n"),
    ("camera.conf", '<?xml version="1.0"?>\n<opencv_storage>\n<image_width>640</image_width>\n'
                    "<image_height>480</image_height>\n<model>pinhole</model>\n</opencv_storage>\n")])
def test_an_opencv_filestorage_file_is_read_by_its_header_whatever_its_name(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    assert read_document(path, None) == {"image_width": 640, "image_height": 480, "model": "pinhole"}
