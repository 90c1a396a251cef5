"""What the stacked datasets share: a ``pre_transform`` that cannot be stored is refused, a
processed file that lacks a field is made again, a release image that is missing or does
not decode is named."""

import cv2
import numpy as np
import pytest
import torch
from torch_geometric.data import Data

from usf_graph.datasets.stacked import load_or_rebuild, pre_transform_stacked, read_release_image


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


SPRUNG = []


def _spring():
    SPRUNG.append(1)
    return 0


class _Trap:
    """Unpickling this calls :func:`_spring`: code a processed file could run if loaded
    with ``weights_only=False``."""

    def __reduce__(self):
        return _spring, ()


def test_a_processed_file_that_would_run_code_is_never_unpickled(tmp_path):
    path = tmp_path / "split.pt"
    torch.save({"x": torch.zeros(2), "y": _Trap()}, path)

    def process():
        torch.save({"x": torch.ones(2), "y": torch.ones(2)}, path)

    with pytest.warns(UserWarning, match=r"unreadable \(UnpicklingError: Unsupported global.*_spring") as w:
        blob = load_or_rebuild(path, process, ("x", "y"))
    assert not SPRUNG and blob["y"].tolist() == [1.0, 1.0]
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
