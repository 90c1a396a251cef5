"""Video files and side-by-side frames."""

import numpy as np
import pytest

from usf_graph.videos import split_frame


def test_split_frame_cuts_side_by_side_cameras_in_order():
    frame = np.arange(4 * 6 * 3).reshape(4, 6, 3)
    parts = split_frame(frame, 3, "rig.yaml")
    assert [p.shape for p in parts] == [(4, 2, 3)] * 3
    assert np.array_equal(np.concatenate(parts, 1), frame) and parts[1][0, 0, 0] == frame[0, 2, 0]
    with pytest.raises(ValueError, match="has one camera"):
        split_frame(frame, 1, "rig.yaml")
    with pytest.raises(ValueError, match="6 pixels wide, which does not cut into 4"):
        split_frame(frame, 4, "rig.yaml")
