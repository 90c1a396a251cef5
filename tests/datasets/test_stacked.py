"""What the stacked datasets share: a ``pre_transform`` that cannot be stored is refused, a
processed file that lacks a field is made again, a release image that is missing or does
not decode is named."""

import inspect

import cv2
import numpy as np
import pytest
import torch
from torch_geometric.data import Data

from tests.helpers import CodeOnLoad
from usf_graph.datasets.stacked import (
    UprightAsReleased,
    add_boxes,
    load_or_rebuild,
    missing_release,
    pack_boxes,
    pre_transform_stacked,
    read_release_image,
)


def _samples():
    pos = torch.rand(5, 3)
    return [Data(x=torch.full((5, 2), float(i)), pos=pos) for i in range(3)]


def test_pre_transform_results_are_stacked_or_refused():
    out = pre_transform_stacked(lambda d: Data(x=2 * d.x, pos=d.pos), _samples(), "x", ("pos",))
    assert out.shape == (3, 5, 2) and out[:, 0, 0].tolist() == [0.0, 2.0, 4.0]
    cases = [(lambda d: None, "pre_transform returned no 'x' for sample 0"),
             (lambda d: Data(pos=d.pos), "returned no 'x' for sample 0"),
             (lambda d: Data(x=d.x[: 5 - int(d.x[0, 0])], pos=d.pos),
              r"changed the shape of 'x' to \(4, 2\) for sample 1 \(sample 0: \(5, 2\)\)"),
             (lambda d: Data(x=d.x, pos=d.pos + 1), "changed 'pos', which all samples share")]
    for pre, why in cases:
        with pytest.raises(ValueError, match=why):
            pre_transform_stacked(pre, _samples(), "x", ("pos",))


def test_a_processed_file_lacking_a_field_is_made_again(tmp_path):
    path = tmp_path / "split.pt"
    torch.save({"x": torch.zeros(2)}, path)

    def process():
        torch.save({"x": torch.ones(2), "y": torch.ones(2)}, path)

    with pytest.warns(UserWarning, match=r"unreadable \(KeyError: .*missing \['y'\].*processing"):
        blob = load_or_rebuild(path, process, ("x", "y"))
    assert blob["y"].tolist() == [1.0, 1.0] and set(torch.load(path, weights_only=True)) == {"x", "y"}
    assert load_or_rebuild(path, lambda: pytest.fail("rebuilt a good file"), ("x", "y"))["x"].sum() == 2


class _Split:
    """Calls ``load_or_rebuild`` from its constructor, as every stacked dataset does."""

    def __init__(self, path, process):
        self.blob = load_or_rebuild(path, process, ("x",))


def test_the_rebuild_warning_points_at_the_line_that_made_the_dataset(tmp_path):
    path = tmp_path / "split.pt"
    path.write_bytes(b"not a torch file")
    with pytest.warns(UserWarning, match="unreadable") as w:
        line = inspect.currentframe().f_lineno + 1
        _Split(path, lambda: torch.save({"x": torch.ones(1)}, path))
    assert (w[0].filename, w[0].lineno) == (__file__, line)


def test_a_processed_file_that_would_run_code_is_never_unpickled(tmp_path):
    path = tmp_path / "split.pt"
    mark = tmp_path / "ran"
    torch.save({"x": torch.zeros(2), "y": CodeOnLoad(mark)}, path)

    def process():
        torch.save({"x": torch.ones(2), "y": torch.ones(2)}, path)

    with pytest.warns(UserWarning, match=r"unreadable \(UnpicklingError: Unsupported global") as w:
        blob = load_or_rebuild(path, process, ("x", "y"))
    assert not mark.exists() and blob["y"].tolist() == [1.0, 1.0]
    # one line, without torch's advice to load it with weights_only=False
    assert "\n" not in str(w[0].message) and "weights_only" not in str(w[0].message)


def test_release_images_missing_or_corrupt_are_named(tmp_path):
    img = np.arange(48, dtype=np.uint8).reshape(4, 4, 3)
    cv2.imwrite(str(tmp_path / "a.png"), img)
    np.testing.assert_array_equal(read_release_image(tmp_path / "a.png", cv2.IMREAD_COLOR, ""), img)
    with pytest.raises(FileNotFoundError, match=r"b.png is missing. Get the release from X"):
        read_release_image(tmp_path / "b.png", cv2.IMREAD_COLOR, "Get the release from X")
    (tmp_path / "c.png").write_bytes((tmp_path / "a.png").read_bytes()[:20])
    with pytest.raises(ValueError, match="c.png is not a readable PNG .* download it again"):
        read_release_image(tmp_path / "c.png", cv2.IMREAD_COLOR, "")


def test_boxes_pack_into_rows_and_come_back_per_sample():
    first = np.arange(10.0).reshape(2, 5)
    store = pack_boxes([first, np.zeros((0, 5)), [0.5, 1.5, 2.5, 3.5, 4.5]], [[3, 1], [], 7])
    assert store["boxes"].shape == (3, 5) and store["box_ptr"].tolist() == [0, 2, 2, 3]
    assert store["box_class"].tolist() == [3, 1, 7] and store["box_class"].dtype == torch.long

    class Store:
        boxes, box_class, box_ptr = store["boxes"], store["box_class"], store["box_ptr"]

    got = [add_boxes(Data(), Store, i) for i in range(3)]
    assert torch.equal(got[0].boxes, torch.as_tensor(first, dtype=torch.float32))
    assert got[1].boxes.shape == (0, 5) and got[1].box_class.tolist() == []
    assert got[2].boxes.tolist() == [[0.5, 1.5, 2.5, 3.5, 4.5]] and got[2].box_class.tolist() == [7]


def test_a_missing_release_names_what_it_lacks_and_how_to_get_it(tmp_path):
    (tmp_path / "annotations").mkdir()
    (tmp_path / "annotations" / "train.json").write_text("{}")

    class Release:
        raw_dir = str(tmp_path)
        raw_file_names = ["annotations/train.json", "images", "annotations/test.json"]

    err = missing_release(Release(), "Download it from the authors.")
    assert str(err) == f"images, annotations/test.json not found under {tmp_path}. Download it from the authors."


def test_panoramas_released_upright_have_up_along_z():
    class Split(UprightAsReleased):
        x = torch.zeros(3, 7, 3)

    g = Split().gravity
    assert g.dtype == torch.float64 and g.tolist() == [[0.0, 0.0, 1.0]] * 3
