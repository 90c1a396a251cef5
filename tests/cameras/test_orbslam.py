"""ORB-SLAM3's settings files: both layouts, the stereo pair's mounting, bad files."""

import math

import numpy as np
import pytest

from tests.helpers import FIXTURES
from usf_graph import cameras as C

STEREO = FIXTURES / "orbslam3_stereo_kb8.yaml"  # File.version 1.0, KannalaBrandt8 pair
MONO = FIXTURES / "orbslam3_mono_pinhole.yaml"  # the older Camera.* layout, PinHole


def test_both_layouts_read_with_their_parameters(tmp_path):
    left, right = C.load(STEREO), C.load(STEREO, key="Camera2")
    assert isinstance(left, C.KannalaBrandt) and (left.width, left.height) == (512, 512)
    assert (left.fx, left.cy) == (190.97847715128717, 256.8974428996504)
    np.testing.assert_array_equal(right.k, [0.0034003170790442797, 0.001766278153469831,
                                            -0.00266312569781606, 0.0003299517423931039])
    mono = C.load(MONO)
    assert isinstance(mono, C.Pinhole) and (mono.fx, mono.width) == (517.306408, 640)
    np.testing.assert_array_equal(mono.dist[:5], [0.262383, -0.953104, -0.005358, 0.002628, 1.163314])
    with pytest.raises(ValueError, match=r"no camera 'Camera2' in the ORB-SLAM3 settings"):
        C.load(MONO, key="Camera2")
    # a PinHole without distortion lines has none (each coefficient defaults to 0)
    text = MONO.read_text()
    lines = [ln for ln in text.splitlines(True) if ln.startswith(("Camera.k", "Camera.p"))]
    assert len(lines) == 5
    (tmp_path / "bare.yaml").write_text("".join(ln for ln in text.splitlines(True) if ln not in lines))
    bare = C.load(tmp_path / "bare.yaml")
    assert isinstance(bare, C.Pinhole) and bare.fx == 517.306408 and not np.any(bare.dist)


def test_the_stereo_pair_is_mounted_by_T_c1_c2():
    rig = C.load_rig(STEREO)
    assert list(rig) == ["Camera1", "Camera2"]
    np.testing.assert_allclose(rig["Camera1"].rotation @ [0.0, 0, 1], [1, 0, 0], atol=1e-12)
    # Camera2 is turned 10 degrees to the right (T_c1_c2 maps its coordinates to Camera1's)
    a = math.radians(10)
    np.testing.assert_allclose(rig["Camera2"].rotation @ [0.0, 0, 1], [math.cos(a), -math.sin(a), 0],
                               atol=1e-6)  # the file stores float32 ("dt: f")


def test_bad_settings_get_clear_errors(tmp_path):
    text = STEREO.read_text()
    for edit, match in ((lambda t: t.replace('"KannalaBrandt8"', '"Omni"'),
                         r"Camera.type 'Omni' is not supported; supported: PinHole"),
                        (lambda t: t.replace("Camera1.k3:", "Camera1.kk3:"), r"missing key 'Camera1.k3'"),
                        (lambda t: t.replace("Camera.width: 512", ""), r"Camera.width and Camera.height")):
        bad = tmp_path / "settings.yaml"
        bad.write_text(edit(text))
        with pytest.raises(ValueError, match=match):
            C.load(bad)
    alone = tmp_path / "no_extrinsics.yaml"
    alone.write_text(text.split("# Transformation matrix")[0] + "Camera.width: 512\nCamera.height: 512\n")
    assert isinstance(C.load(alone, key="Camera2"), C.KannalaBrandt)  # unmounted, but readable
    with pytest.raises(ValueError, match=r"\[Camera2\]: no 'Stereo.T_c1_c2' \(or 'Tlr'\)"):
        C.load_rig(alone)
