"""Calibration files in the formats users have, and bad inputs."""

import math

import numpy as np
import pytest

from tests.helpers import FIXTURES
from usf_graph import cameras as C

FIX = FIXTURES


def test_kalibr_camchain_all_supported_models():
    c0 = C.load(FIX / "kalibr_camchain.yaml")
    assert isinstance(c0, C.Pinhole) and c0.fx == 458.654 and (c0.width, c0.height) == (752, 480)
    np.testing.assert_allclose(c0.dist[:4], [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05])
    c1 = C.load(FIX / "kalibr_camchain.yaml", key="cam1")
    assert isinstance(c1, C.KannalaBrandt) and c1.k[0] == pytest.approx(0.0034823894022493434)
    c2 = C.load(FIX / "kalibr_camchain.yaml", key="cam2")
    assert isinstance(c2, C.Mei) and c2.xi == 0.8 and c2.fx == 520.1 and c2.dist[0] == -0.0302
    c3 = C.load(FIX / "kalibr_camchain.yaml", key="cam3")
    assert isinstance(c3, C.DoubleSphere) and (c3.xi, c3.alpha, c3.fx, c3.cy) == (-0.2, 0.59, 313.2, 511.2)
    assert c3.fov_deg > 180
    with pytest.raises(ValueError, match="eucm"):
        C.load(FIX / "kalibr_camchain.yaml", key="cam4")
    with pytest.raises(ValueError, match="no camera 'cam9'"):
        C.load(FIX / "kalibr_camchain.yaml", key="cam9")


def test_opencv_filestorage_yaml_and_xml():
    cam = C.load(FIX / "opencv_pinhole.yaml")
    assert isinstance(cam, C.Pinhole) and (cam.width, cam.height) == (1280, 720)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (912.34, 910.87, 640.12, 360.55)
    np.testing.assert_allclose(cam.dist[[0, 1, 2, 3, 4]], [-0.1021, 0.0873, 0.0011, -0.0007, -0.0213])
    fe = C.load(FIX / "opencv_fisheye.xml")
    assert isinstance(fe, C.KannalaBrandt)
    np.testing.assert_allclose(fe.k, [0.0211, -0.0042, 0.0007, -0.0001])


@pytest.mark.parametrize("name, cls, ncoef", [("ros_plumb_bob.yaml", C.Pinhole, 5),
                                               ("ros_rational.yaml", C.Pinhole, 8),
                                               ("ros_equidistant.yaml", C.KannalaBrandt, 4)])
def test_ros_camera_info(name, cls, ncoef):
    cam = C.load(FIX / name)
    assert type(cam) is cls and (cam.width, cam.height) == (640, 480)
    if cls is C.Pinhole:
        assert cam._ncoef == ncoef and cam.dist[0] == -0.2812
        assert cam.fx == 520.1 and cam.cy == 241.7


def test_ocamcalib_calib_results():
    cam = C.load(FIX / "calib_results.txt")
    assert isinstance(cam, C.Scaramuzza) and (cam.width, cam.height) == (1280, 960)
    np.testing.assert_allclose(cam.pol, [-244.5529, 0, 1.580042e-03, -2.461564e-06, 8.933961e-09])
    assert cam.center.tolist() == [479.508480, 639.418160]
    # the centre looks down the optical axis; invpol (a fitted approximation of the
    # forward map) agrees with our exact Newton projection to a fraction of a pixel
    r, ok = cam.unproject(np.array([[639.41816, 479.50848]]))
    np.testing.assert_allclose(r[0], [0, 0, 1], atol=1e-12)
    rng = np.random.default_rng(0)
    uv = np.stack([rng.uniform(200, 1000, 200), rng.uniform(150, 800, 200)], -1)
    rays, ok = cam.unproject(uv)
    assert ok.all()
    theta = np.arctan2(-rays[:, 2], np.hypot(rays[:, 0], rays[:, 1]))  # OCamCalib's angle
    rho = np.polynomial.polynomial.polyval(theta, cam.invpol)
    rho_exact = np.hypot(*cam._sensor(uv))
    assert np.abs(rho - rho_exact).max() < 0.5
    assert cam.fov_deg > 180


@pytest.mark.parametrize("cam", [
    C.Pinhole(500, 501, 320, 240, 640, 480, dist=[0.1, -0.05, 1e-3, 2e-4, 0.01, 0.0, 0.0, 0.0]),
    C.KannalaBrandt(300, 300, 640, 480, 1280, 960, k=(0.01, 0.0, 0.0, 0.0), fov_deg=190),
    C.Fisheye(250, 300, 300, 600, 600, model="equisolid", fov_deg=180),
    C.Mei(400, 400, 640, 480, 1280, 960, xi=1.2, dist=(0.01, 0, 0, 0), skew=0.5),
    C.DoubleSphere(300, 300, 640, 480, 1280, 960, xi=-0.2, alpha=0.6),
    C.Equirectangular(512, 256, lat_range=(-1.0, 1.2)),
    C.Scaramuzza([-250.0, 0.0, 1e-3], (240, 320), (1, 0, 0), 640, 480),
])
def test_own_yaml_round_trip(tmp_path, cam):
    rot = cam.rotation @ np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    cam = cam.with_rotation(rot)
    cam.save(tmp_path / "cam.yaml")
    back = C.load(tmp_path / "cam.yaml")
    assert type(back) is type(cam) and back.key() == cam.key()
    uv = cam.pixel_grid()[::37, ::41].reshape(-1, 2)
    np.testing.assert_allclose(back.unproject(uv)[0], cam.unproject(uv)[0], atol=1e-14)


def test_lens_normal_map_files(tmp_path):
    ref = C.Fisheye(40, 31.5, 23.5, 64, 48, fov_deg=200)
    rays, valid = ref.unproject(ref.pixel_grid())
    np.savez(tmp_path / "lnm.npz", rays=rays, valid=valid)
    np.save(tmp_path / "lnm.npy", np.nan_to_num(rays))
    for name in ("lnm.npz", "lnm.npy"):
        cam = C.load(tmp_path / name)
        assert isinstance(cam, C.LensNormalMap)
        assert cam.valid_table.sum() == valid.sum()
        assert cam.fov_deg == pytest.approx(ref.fov_deg, abs=3)
    np.savez(tmp_path / "bad.npz", other=rays)
    with pytest.raises(ValueError, match="no 'rays'"):
        C.load(tmp_path / "bad.npz")
    (tmp_path / "corrupt.npy").write_bytes(b"\x93NUMPY garbage")
    with pytest.raises(ValueError, match="cannot read"):
        C.load(tmp_path / "corrupt.npy")


def test_bad_files_raise_clear_errors(tmp_path):
    p = tmp_path / "a.yaml"
    p.write_text("usf_graph_camera: 1\nmodel: Spherinator\nparams: {}\n")
    with pytest.raises(ValueError, match="unknown camera model 'Spherinator'"):
        C.load(p)
    p.write_text("image_width: 640\nimage_height: 480\ncamera_matrix: {rows: 3, cols: 3, "
                 "data: [1,0,0,0,1,0,0,0,1]}\ndistortion_coefficients: {data: []}\n")
    with pytest.raises(ValueError, match="missing key 'distortion_model'"):
        C.load(p)
    p.write_text(p.read_text() + "distortion_model: magic\n")
    with pytest.raises(ValueError, match="unknown ROS distortion_model 'magic'"):
        C.load(p)
    k = (FIX / "kalibr_camchain.yaml").read_text().replace("  resolution: [752, 480]\n", "")
    p.write_text(k)
    with pytest.raises(ValueError, match="missing key 'resolution' in cam0"):
        C.load(p)
    o = (FIX / "opencv_pinhole.yaml").read_text().replace("image_width: 1280\n", "")
    q = tmp_path / "o.yaml"
    q.write_text(o)
    with pytest.raises(ValueError, match="missing key 'image_width'"):
        C.load(q)
    t = tmp_path / "calib_results.txt"
    t.write_text((FIX / "calib_results.txt").read_text().replace("5 -2.445529e+02", "7 -2.445529e+02"))
    with pytest.raises(ValueError, match="malformed OCamCalib"):
        C.load(t)
    p.write_text("just: [a, list\n")
    with pytest.raises(ValueError, match="not valid YAML"):
        C.load(p)
    with pytest.raises(FileNotFoundError):
        C.load(tmp_path / "nope.yaml")
    p.write_text("cam0: {camera_model: pinhole, intrinsics: [-5, 400, 320, 240], "
                 "distortion_model: none, resolution: [640, 480]}\n")
    with pytest.raises(ValueError, match="fx must be a positive"):
        C.load(p)
    assert math.isfinite(C.load(FIX / "ros_plumb_bob.yaml").fov_deg)
