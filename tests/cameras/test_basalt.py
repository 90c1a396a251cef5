"""Basalt's calibration JSON: models, the rig's mounting, and bad files."""

import json

import numpy as np
import pytest

from tests.helpers import FIXTURES
from usf_graph import cameras as C
from usf_graph.cli import main

FILE = FIXTURES / "basalt_calib.json"


def test_every_camera_type_reads_with_its_parameters():
    ds, kb, radtan, unified = (C.load(FILE, key=f"cam{i}") for i in range(4))
    assert C.load(FILE).key() == ds.key()  # cam0 by default
    assert isinstance(ds, C.DoubleSphere) and (ds.fx, ds.cy, ds.xi, ds.alpha) == (158.3, 256.8, -0.172, 0.593)
    assert (ds.width, ds.height) == (512, 512) and ds.fov_deg > 180
    assert isinstance(kb, C.KannalaBrandt) and (kb.width, kb.height) == (848, 800)
    np.testing.assert_array_equal(kb.k, [-0.0067, 0.045, -0.043, 0.0083])
    assert isinstance(radtan, C.Pinhole)  # OpenCV order: k1 k2 p1 p2 k3 k4 k5 k6
    np.testing.assert_array_equal(radtan.dist[:8], [-0.2, 0.05, 1e-05, -2e-05, 0, 0, 0, 0])
    # the unified model (alpha form) is Mei's with xi = alpha / (1 - alpha), gamma = f / (1 - alpha)
    assert isinstance(unified, C.EUCM) and unified.beta == 1.0
    mei = C.Mei(300 / 0.4, 300 / 0.4, 320, 240, 640, 480, xi=0.6 / 0.4)
    rays = np.random.default_rng(0).normal(size=(500, 3)) + [0, 0, 1.5]
    a, ok_a = unified.project(rays)
    b, ok_b = mei.project(rays)
    assert ok_a.mean() > 0.9 and (ok_a == ok_b).all()  # the same domain, past 90 degrees
    np.testing.assert_allclose(a[ok_a], b[ok_a], atol=1e-9)


def test_the_rig_mounts_each_camera_by_its_imu_pose():
    rig = C.load_rig(FILE)
    assert list(rig) == ["cam0", "cam1", "cam2", "cam3"]
    axis = {n: cam.rotation @ [0.0, 0.0, 1.0] for n, cam in rig.items()}  # optical axes
    np.testing.assert_allclose(axis["cam0"], [1, 0, 0], atol=1e-12)  # the sphere's forward
    np.testing.assert_allclose(axis["cam1"], [-1, 0, 0], atol=1e-12)  # turned around
    np.testing.assert_allclose(axis["cam2"], [0, 1, 0], atol=1e-12)  # to the left
    np.testing.assert_allclose(rig["cam3"].rotation, rig["cam0"].rotation, atol=1e-12)
    # image down stays down for the camera turned about its y axis
    np.testing.assert_allclose(rig["cam1"].rotation @ [0.0, 1.0, 0.0], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(C.load(FILE, key="cam2").rotation, rig["cam2"].rotation)


def test_bad_basalt_files_get_clear_errors(tmp_path):
    doc = json.loads(FILE.read_text())
    with pytest.raises(ValueError, match=r"no camera 'cam7' in the Basalt calibration .*--key"):
        C.load(FILE, key="cam7")

    def broken(edit, match, rig=False):
        d = json.loads(json.dumps(doc))
        edit(d["value0"])
        path = tmp_path / "calib.json"
        path.write_text(json.dumps(d))
        with pytest.raises(ValueError, match=match):
            (C.load_rig if rig else lambda p: C.load(p, key="cam1"))(path)

    broken(lambda v: v["intrinsics"][1].update(camera_type="fov"),
           r"\[cam1\]: Basalt camera_type 'fov' is not supported; supported: pinhole")
    broken(lambda v: v["intrinsics"][1]["intrinsics"].pop("k3"), r"missing key 'k3' in 'intrinsics'")
    broken(lambda v: v["intrinsics"][1]["intrinsics"].update(xi=0.1), r"unexpected \['xi'\]")
    broken(lambda v: v.update(resolution=[[512, 512]]), r"lists 1 cameras' sizes")
    broken(lambda v: v["T_imu_cam"][1].update(qw=3.0), r"quaternion of norm")
    broken(lambda v: v.pop("T_imu_cam"), r"\[cam1\]: no 'T_imu_cam' for it", rig=True)
    bad = tmp_path / "bad.json"
    bad.write_text('{"value0": {"intrinsics": [}')
    with pytest.raises(ValueError, match="not valid JSON"):
        C.load(bad)


def test_cli_describes_a_basalt_camera(capsys):
    assert main(["camera", str(FILE), "--key", "cam1"]) == 0
    assert "kannala-brandt" in capsys.readouterr().out.lower()
