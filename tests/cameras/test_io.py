"""Calibration files in the formats users have, and bad inputs."""

import math

import cv2
import numpy as np
import pytest
import yaml

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
    c4 = C.load(FIX / "kalibr_camchain.yaml", key="cam4")  # [alpha, beta, fu, fv, pu, pv]
    assert isinstance(c4, C.EUCM) and (c4.alpha, c4.beta, c4.fx, c4.fy, c4.cx, c4.cy) == \
        (0.6, 1.1, 300, 300, 320, 240) and (c4.width, c4.height) == (640, 480)
    with pytest.raises(ValueError, match=r"no camera 'cam9'.*--key"):
        C.load(FIX / "kalibr_camchain.yaml", key="cam9")


def test_kalibr_extrinsics_mount_each_camera_in_the_rig():
    chain = FIX / "kalibr_camchain.yaml"
    c0, c1 = C.load(chain), C.load(chain, key="cam1")
    np.testing.assert_array_equal(c0.rotation, C.DEFAULT_ROTATION)  # cam0 looks along +x
    T = np.array([[0.999997256477, 0.002312067192, 0.000376008102],
                  [-0.002317135723, 0.999898048507, 0.014089835846],
                  [-0.000343393121, -0.014090668452, 0.999900662637]])
    np.testing.assert_allclose(c1.rotation, C.DEFAULT_ROTATION @ T.T, atol=1e-8)
    # a camera without extrinsics keeps the default mounting
    np.testing.assert_array_equal(C.load(chain, key="cam2").rotation, C.DEFAULT_ROTATION)
    rig = C.load_rig(FIX / "kalibr_rig.yaml")
    assert list(rig) == ["cam0", "cam1"]
    axes = [cam.rotation @ [0, 0, 1.0] for cam in rig.values()]  # optical axes, sphere frame
    np.testing.assert_allclose(axes, [[1, 0, 0], [-1, 0, 0]], atol=1e-15)
    # the back camera's image right is the rig's +y (left when seen from the front)
    np.testing.assert_allclose(rig["cam1"].rotation @ [1.0, 0, 0], [0, 1, 0], atol=1e-15)
    with pytest.raises(ValueError, match=r"\[cam2\].*T_cn_cnm1"):
        C.load_rig(chain)


def test_kalibr_omni_without_distortion_and_a_chain_with_an_imu_section(tmp_path):
    """omni-none is Mei without distortion; a mapping that is not a camera (an IMU's
    section) is not one of the chain's cameras."""
    text = (FIX / "kalibr_camchain.yaml").read_text()
    radtan = "distortion_coeffs: [-0.0302, 0.0125, 0.0004, -0.0003]\n  distortion_model: radtan"
    assert radtan in text
    (tmp_path / "omni.yaml").write_text(text.replace(radtan, "distortion_coeffs: []\n  distortion_model: none"))
    mei = C.load(tmp_path / "omni.yaml", key="cam2")
    assert isinstance(mei, C.Mei) and mei.xi == 0.8 and not np.any(mei.dist)
    (tmp_path / "imu.yaml").write_text((FIX / "kalibr_rig.yaml").read_text() +
                                       "imu0:\n  rostopic: /imu0\n  update_rate: 200.0\n")
    assert list(C.load_rig(tmp_path / "imu.yaml")) == ["cam0", "cam1"]


def test_kalibr_rig_from_the_imu_extrinsics_alone(tmp_path):
    """Without T_cn_cnm1, each camera is mounted from both cameras' T_cam_imu: the rig is
    the one the same chain written with T_cn_cnm1 (cam1 <- cam0) gives."""
    rng = np.random.default_rng(3)

    def rigid():
        q = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = q * np.sign(np.linalg.det(q)), rng.normal(size=3) * 0.1
        return T

    T0, T1 = rigid(), rigid()  # cam <- IMU
    cam = yaml.safe_load((FIX / "kalibr_rig.yaml").read_text())["cam0"]
    (tmp_path / "imu.yaml").write_text(yaml.safe_dump(
        {"cam0": {**cam, "T_cam_imu": T0.tolist()}, "cam1": {**cam, "T_cam_imu": T1.tolist()}}))
    (tmp_path / "chain.yaml").write_text(yaml.safe_dump(
        {"cam0": cam, "cam1": {**cam, "T_cn_cnm1": (T1 @ np.linalg.inv(T0)).tolist()}}))
    imu, chain = C.load_rig(tmp_path / "imu.yaml"), C.load_rig(tmp_path / "chain.yaml")
    assert not np.allclose(imu["cam1"].rotation, imu["cam0"].rotation, atol=0.1)
    for k in ("cam0", "cam1"):
        np.testing.assert_allclose(imu[k].rotation, chain[k].rotation, atol=1e-12)
        np.testing.assert_allclose(imu[k].position, chain[k].position, atol=1e-12)


def test_opencv_calibration_sample_fisheye_model_flag():
    cam = C.load(FIX / "opencv_sample_fisheye.yaml")  # fisheye_model: 1, no distortion_model
    assert isinstance(cam, C.KannalaBrandt) and (cam.width, cam.height) == (1280, 960)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (331.27, 331.09, 641.35, 480.72)
    np.testing.assert_array_equal(cam.k, [0.0312, -0.0104, 0.0021, -0.0003])
    assert cam.fov_deg > 180  # a fisheye, not a pinhole with four radtan coefficients


def test_cv2_omnidir_file_with_xi_as_a_matrix():
    cam = C.load(FIX / "omnidir_calibration.yml")
    assert isinstance(cam, C.Mei) and (cam.width, cam.height) == (1280, 960)
    assert (cam.xi, cam.fx, cam.fy, cam.cx, cam.cy, cam.skew) == \
        (1.2153, 702.15, 701.63, 640.82, 479.11, 0.35)
    np.testing.assert_array_equal(cam.dist[:4], [-0.2341, 0.0912, 0.0012, -0.0007])


def test_k_d_dim_files_as_yaml_filestorage_and_npz(tmp_path):
    ref = C.load(FIX / "fisheye_kdd.yaml")
    assert isinstance(ref, C.KannalaBrandt) and (ref.width, ref.height) == (1280, 960)
    np.testing.assert_array_equal(ref.k, [0.0312, -0.0104, 0.0021, -0.0003])
    K = np.array([[331.27, 0, 641.35], [0, 331.09, 480.72], [0, 0, 1.0]])
    D = np.array([[0.0312], [-0.0104], [0.0021], [-0.0003]])
    np.savez(tmp_path / "calib.npz", K=K, D=D, DIM=np.array([1280, 960]))
    fs = cv2.FileStorage(str(tmp_path / "calib.yaml"), cv2.FILE_STORAGE_WRITE)
    fs.write("K", K), fs.write("D", D), fs.write("DIM", np.array([[1280, 960]], np.float64))
    fs.release()
    for name in ("calib.npz", "calib.yaml"):
        assert C.load(tmp_path / name).key() == ref.key()
    np.savez(tmp_path / "pin.npz", K=K, D=np.array([0.1, -0.05, 1e-3, 2e-4, 0.01]), DIM=[1280, 960])
    assert isinstance(C.load(tmp_path / "pin.npz"), C.Pinhole)  # 5 coefficients: radtan
    # DIM as a FileStorage sequence (a hand-written file), beside a string node it ignores
    text = (tmp_path / "calib.yaml").read_text()
    seq = text[:text.index("DIM:")] + 'DIM: [ 1280, 960 ]\nmodel: "fisheye"\n'
    (tmp_path / "seq.yaml").write_text(seq)
    assert C.load(tmp_path / "seq.yaml").key() == ref.key()
    (tmp_path / "seq.yaml").write_text(seq.replace("1280, 960", "1280.5, 960"))
    with pytest.raises(ValueError, match="DIM"):
        C.load(tmp_path / "seq.yaml")


def test_usf_reference_sensor_yaml(tmp_path):
    cam = C.load(FIX / "usf_sensor_mei.yaml")
    assert isinstance(cam, C.Mei) and (cam.width, cam.height) == (612, 514)
    assert (cam.xi, cam.fx, cam.fy, cam.cx, cam.cy) == (1.7993, 409.006, 409.004, 304.715, 255.533)
    np.testing.assert_array_equal(cam.dist[:4], [-0.09541, 0.20030, 5.52e-4, 2.17e-5])
    mask = cv2.imread(str(FIX / "usf_sensor_mask.png"), cv2.IMREAD_GRAYSCALE) > 0
    np.testing.assert_array_equal(cam.image_mask, mask)
    _, seen = cam.lens_normal_map()
    assert not seen[0, 0] and seen[256, 305]  # the mask is applied, to the coverage too
    whole = cam.with_image_mask(None)
    assert cam.solid_angle() < whole.solid_angle() and cam.fov_deg < whole.fov_deg - 20
    # model_type 0 is a pinhole; a lens_normal_map next to the file replaces the model
    text = (FIX / "usf_sensor_mei.yaml").read_text().replace("mask: usf_sensor_mask.png\n", "")
    pin = text.replace("model_type: 1", "model_type: 0").replace("gamma1", "fx") \
        .replace("gamma2", "fy").replace("u0", "cx").replace("v0", "cy")
    (tmp_path / "pin.yaml").write_text(pin)
    p = C.load(tmp_path / "pin.yaml")
    assert isinstance(p, C.Pinhole) and (p.fx, p.cy, p.dist[3]) == (409.006, 255.533, 2.17e-5)
    rays, _ = C.Fisheye(200, 305, 256, 612, 514, fov_deg=180).unproject(
        C.Pinhole(1, 1, 0, 0, 612, 514).pixel_grid())
    np.save(tmp_path / "lnm.npy", np.nan_to_num(rays))
    (tmp_path / "lnm.yaml").write_text(text + "lens_normal_map: lnm.npy\n")
    assert isinstance(C.load(tmp_path / "lnm.yaml"), C.LensNormalMap)
    np.save(tmp_path / "lnm.npy", np.nan_to_num(rays[:100]))
    with pytest.raises(ValueError, match=r"lnm.yaml: lens_normal_map is 612 x 100"):
        C.load(tmp_path / "lnm.yaml")


def test_fov_and_mask_from_files_and_arguments(tmp_path):
    kb = C.load(FIX / "kalibr_rig.yaml")  # equidistant to the sensor's corners
    assert kb.fov_deg == pytest.approx(270, abs=2)
    cut = C.load(FIX / "kalibr_rig.yaml", fov_deg=190)
    assert cut.fov_deg == pytest.approx(190, abs=0.5)
    rays, ok = cut.unproject(cut.pixel_grid())
    assert ok.sum() < kb.unproject(kb.pixel_grid())[1].sum()
    mask = np.zeros((400, 400), bool)
    mask[50:350, 50:350] = True
    cam = cut.with_image_mask(mask)
    cam.save(tmp_path / "cam.yaml")
    assert "fov_deg: 190" in (tmp_path / "cam.yaml").read_text()
    back = C.load(tmp_path / "cam.yaml")
    assert back.key() == cam.key() and (back.image_mask == mask).all()
    np.testing.assert_array_equal(back.lens_normal_map()[1], cam.lens_normal_map()[1])
    assert C.load(tmp_path / "cam.yaml", image_mask=tmp_path / "cam.mask.png").key() == cam.key()


_KB4 = "cols: 4\n  data: [0.021, -0.0042, 0.0007, -0.0001]"  # ros_equidistant.yaml's D
BROKEN = [
    ("opencv_sample_fisheye.yaml", "image_width: 1280\n", "", "missing key 'image_width'"),
    ("omnidir_calibration.yml", "rows: 1\n   cols: 1\n   dt: d\n   data: [ 1.2153 ]",
     "rows: 1\n   cols: 2\n   dt: d\n   data: [ 1.2153, 1.0 ]", "'xi' must be one number"),
    ("fisheye_kdd.yaml", "DIM: [1280, 960]\n", "", "missing key 'DIM'"),
    ("fisheye_kdd.yaml", "[[0.0312], [-0.0104], [0.0021], [-0.0003]]", "[0.0312, 0.1, -0.0104]",
     "'D' must have 4 or 5 or 8 or 12 elements, got 3"),
    ("kalibr_camchain.yaml", "intrinsics: [0.8, 520.1", "intrinsics: [520.1",
     r"\[cam2\]: Kalibr 'omni' intrinsics are \[xi, fu, fv, pu, pv\] \(5 values\), got 4: "
     r"\[520.1, 519.8, 640.3, 480.7\]"),
    ("kalibr_camchain.yaml", "- [0.0, 0.0, 0.0, 1.0]\n  camera_model: pinhole\n  distortion_coeffs: [0.0034",
     "- [0.0, 0.0, 0.0, 1.0]\n  camera_model: pinhole\n  distortion_coeffs: [0.0034, 0.1",
     r"\[cam1\]: Kalibr distortion_model 'equidistant' takes 4 distortion_coeffs, got 5"),
    ("kalibr_camchain.yaml", "[0.999997256477, 0.002312067192", "[2.999997256477, 0.002312067192",
     r"\[cam1\]: 'T_cn_cnm1' is not a rigid transform"),
    ("kalibr_camchain.yaml", "camera_model: pinhole", "camera_model: fov",
     "unknown Kalibr camera_model 'fov'; supported: pinhole, omni, ds, eucm"),
    ("kalibr_camchain.yaml", "distortion_model: radtan", "distortion_model: fov",
     "Kalibr pinhole-fov is not supported; supported: pinhole-radtan"),
    ("ros_equidistant.yaml", _KB4, "cols: 5\n  data: [0.021, -0.0042, 0.0007, -0.0001, 0.5]",
     r"'distortion_coefficients' has 5 coefficients but this model uses 4; the extra ones are not "
     r"zero: \[0.5\]"),
    ("ros_equidistant.yaml", _KB4, "cols: 1\n  data: [0.021]",
     "'distortion_coefficients' must have 4 coefficients, got 1"),
    ("usf_sensor_mei.yaml", "model_type: 1", "model_type: 7", r"unknown model_type 7; supported: 0"),
    ("usf_sensor_mei.yaml", "  model_type: 1\n", "", "missing key 'model_type' in 'intrinsic'"),
    ("usf_sensor_mei.yaml", "    gamma1: 409.006\n", "", "missing key 'gamma1' in 'projection_parameters'"),
    ("usf_sensor_mei.yaml", "gamma1: 409.006", "gamma1: -330.0", r"fx must be a positive finite number, got -330.0\."),
    ("usf_sensor_mei.yaml", "usf_sensor_mask.png", "nothing.png", "cannot read the image mask"),
    # image sizes that are not whole pixels are refused, not truncated
    ("kalibr_camchain.yaml", "resolution: [512, 512]", "resolution: [512.5, 512]",
     r"\[cam1\]: 'resolution' must be whole positive numbers of pixels, got \[512.5, 512"),
    ("opencv_pinhole.yaml", "image_width: 1280", "image_width: 1279.6",
     "'image_width' must be whole positive numbers of pixels, got \\[1279.6\\]"),
    ("ros_plumb_bob.yaml", "image_width: 640", "image_width: 0", "'image_width' must be whole positive"),
    ("vins_pinhole.yaml", "image_width: 752", "image_width: 752.25", "'image_width' must be whole"),
    ("orbslam3_mono_pinhole.yaml", "Camera.width: 640", "Camera.width: 640.5",
     "'Camera.width' must be whole positive numbers of pixels"),
    ("nerfstudio_transforms.json", '"w": 876', '"w": 876.4', "'w' must be whole positive numbers"),
    ("calib_results.txt", "960 1280", "960 1280.5", "'height width' must be whole positive numbers"),
    ("calib_results.txt", "479.508480 639.418160", "479.508480 639.418160 1.0",
     "malformed OCamCalib calib_results.txt .*expected 'row col' centre"),
    ("basalt_calib.json", "                848,", "                848.5,",
     r"\[cam1\]: 'resolution' must be whole positive numbers of pixels, got \[848.5, 800"),
]


@pytest.mark.parametrize("name, old, new, match", BROKEN)
def test_broken_files_name_the_file_and_the_key(tmp_path, name, old, new, match):
    text = (FIX / name).read_text()
    assert old in text
    bad = tmp_path / name
    bad.write_text(text.replace(old, new, 1))
    for f in FIX.glob("usf_sensor_mask.png"):
        (tmp_path / f.name).write_bytes(f.read_bytes())
    key = "cam2" if "omni'" in match else ("cam1" if "[cam1" in match.replace("\\", "") else None)
    with pytest.raises(ValueError, match=match) as e:
        C.load(bad, key=key)
    assert str(bad) in str(e.value) and "np.float64" not in str(e.value)


@pytest.mark.parametrize("name, kind", [("opencv_pinhole.yaml", "an OpenCV"), ("usf_sensor_mei.yaml", "a USF sensor"),
                                        ("ros_plumb_bob.yaml", "a ROS camera_info")])
def test_key_for_a_single_camera_file_is_an_error(name, kind):
    with pytest.raises(ValueError, match=rf"key='cam1' \(--key\).*this is {kind} file with one camera"):
        C.load(FIX / name, key="cam1")


def test_distortion_padded_missing_or_unknown(tmp_path):
    """Zero coefficients past a model's count (OpenCV pads to 5 or 8) are read (a non-zero
    one is refused: BROKEN); no coefficients at all, or a USF sensor file without
    distortion_parameters, mean no distortion; a stray model_type does not make a K/D/DIM
    file a USF sensor one; an unknown model names the supported ones."""
    p = tmp_path / "c.yaml"

    def load(text):
        p.write_text(text)
        return C.load(p)

    ros, four = (FIX / "ros_equidistant.yaml").read_text(), _KB4
    assert four in ros
    assert load(ros.replace(four, "cols: 5\n  data: [0.021, -0.0042, 0.0007, -0.0001, 0]")).key() == \
        C.load(FIX / "ros_equidistant.yaml").key()
    assert np.array_equal(load(ros.replace(four, "cols: 0\n  data: []")).k, np.zeros(4))
    usf = (FIX / "usf_sensor_mei.yaml").read_text().replace("mask: usf_sensor_mask.png\n", "")
    mei = load(usf[:usf.index("  distortion_parameters")] + usf[usf.index("  projection_parameters"):])
    assert isinstance(mei, C.Mei) and mei.xi == 1.7993 and not np.any(mei.dist)
    kdd = "K: [300, 0, 320, 0, 300, 240, 0, 0, 1]\nD: [0.1, 0, 0, 0]\nDIM: [640, 480]\n"
    cam = load(kdd + "model_type: fisheye\n")
    assert isinstance(cam, C.KannalaBrandt) and cam.k[0] == 0.1
    with pytest.raises(ValueError, match="unknown distortion_model 'magic'; supported: plumb_bob, "
                                         "rational_polynomial, pinhole, radtan, equidistant, fisheye"):
        load(kdd + "distortion_model: magic\n")


def test_own_files_with_bad_parameters_or_placement(tmp_path):
    """usf-graph's own YAML: a model's refusal of its parameters and a bad position or
    distance are errors that name the file."""
    p = tmp_path / "cam.yaml"
    C.save(C.Pinhole(300, 300, 320, 240, 640, 480).with_position([0.1, 0, 0]), p)
    text = p.read_text()
    assert "fx: 300.0" in text and "- 0.1\n- 0.0\n- 0.0\n" in text
    for old, new, match in (("fx: 300.0", "fx: -300.0", r"bad parameters for Pinhole \(fx must be"),
                            ("fx: 300.0", "f_x: 300.0", "bad parameters for Pinhole .*f_x"),
                            ("- 0.1\n- 0.0\n- 0.0\n", "- 0.1\n- 0.0\n", "position must be 3 numbers"),
                            ("usf_graph_camera: 1\n", "usf_graph_camera: 1\ndistance: -2\n", "distance")):
        p.write_text(text.replace(old, new))
        with pytest.raises(ValueError, match=match) as e:
            C.load(p)
        assert str(p) in str(e.value)


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
    C.EUCM(300, 300, 640, 480, 1280, 960, alpha=0.6, beta=1.1),
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
    with pytest.raises(ValueError, match="missing key 'distortion_model'; ROS camera_info needs one of "
                                         "plumb_bob, rational_polynomial, equidistant"):
        C.load(p)
    p.write_text(p.read_text() + "distortion_model: magic\n")
    with pytest.raises(ValueError, match="unknown ROS distortion_model 'magic'"):
        C.load(p)
    k = (FIX / "kalibr_camchain.yaml").read_text().replace("  resolution: [752, 480]\n", "")
    p.write_text(k)
    with pytest.raises(ValueError, match=r"\[cam0\]: missing key .resolution."):
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
    p.write_text("- fx: 400\n- fy: 400\n")
    with pytest.raises(ValueError, match=r"a.yaml: unrecognized calibration file \(expected a YAML mapping\)"):
        C.load(p)
    p.write_text("%YAML:1.0\n---\nK: !!opencv-matrix\n   rows: 3\n   cols: [3\n")
    with pytest.raises(ValueError, match="a.yaml: OpenCV cannot parse this FileStorage file"):
        C.load(p)
    (tmp_path / "calib.npz").write_bytes(b"PK\x03\x04 not a zip archive")
    with pytest.raises(ValueError, match="cannot read .*calib.npz"):
        C.load(tmp_path / "calib.npz")
    with pytest.raises(FileNotFoundError):
        C.load(tmp_path / "nope.yaml")
    p.write_text("cam0: {camera_model: pinhole, intrinsics: [-5, 400, 320, 240], "
                 "distortion_model: none, resolution: [640, 480]}\n")
    with pytest.raises(ValueError, match="fx must be a positive"):
        C.load(p)
    assert math.isfinite(C.load(FIX / "ros_plumb_bob.yaml").fov_deg)


def test_vins_fusions_camodocal_files_project_as_opencv_does():
    """VINS-Mono's and VINS-Fusion's camera files (CamOdoCal's FileStorage YAML): its
    KANNALA_BRANDT is ``cv2.fisheye`` with k2..k5 and mu mv u0 v0, its PINHOLE is
    ``cv2.projectPoints`` with k1 k2 p1 p2."""
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(3000, 3)) + [0, 0, 2.5]  # ahead of the camera (optical frame)
    pts = pts[pts[:, 2] > 0.6 * np.linalg.norm(pts, axis=-1)]  # within 53 degrees
    for name, kind in (("vins_kannala_brandt.yaml", C.KannalaBrandt), ("vins_pinhole.yaml", C.Pinhole)):
        fs = cv2.FileStorage(str(FIX / name), cv2.FILE_STORAGE_READ)
        p = fs.getNode("projection_parameters")
        cam = C.load(FIX / name)
        assert type(cam) is kind and (cam.width, cam.height) == (int(fs.getNode("image_width").real()),
                                                                   int(fs.getNode("image_height").real()))
        if kind is C.KannalaBrandt:
            K = np.array([[p.getNode("mu").real(), 0, p.getNode("u0").real()],
                          [0, p.getNode("mv").real(), p.getNode("v0").real()], [0, 0, 1]])
            D = np.array([p.getNode(k).real() for k in ("k2", "k3", "k4", "k5")])
            want = cv2.fisheye.projectPoints(pts[:, None], np.zeros(3), np.zeros(3), K, D)[0][:, 0]
        else:
            d = fs.getNode("distortion_parameters")
            K = np.array([[p.getNode("fx").real(), 0, p.getNode("cx").real()],
                          [0, p.getNode("fy").real(), p.getNode("cy").real()], [0, 0, 1]])
            D = np.array([d.getNode(k).real() for k in ("k1", "k2", "p1", "p2")])
            want = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, D)[0][:, 0]
        got, valid = cam.project(pts)
        assert valid.all(), name
        np.testing.assert_allclose(got, want, atol=1e-6, rtol=0, err_msg=name)


def test_rig_topics_need_every_camera_to_name_its_topic(tmp_path):
    text = (FIX / "kalibr_rig.yaml").read_text()
    assert C.rig_topics(FIX / "kalibr_rig.yaml") == ["/front/image_raw", "/back/image_raw"]
    for topic in ('""', "7"):  # empty, or not a name
        bad = tmp_path / f"chain_{len(topic)}.yaml"
        bad.write_text(text.replace("rostopic: /back/image_raw", f"rostopic: {topic}"))
        assert C.rig_topics(bad) is None
