"""Rigs whose cameras are apart: every file format's translations, checked against OpenCV and
pycolmap projecting the same scene points, and the parallax of a finite distance."""

import json
import sys

import cv2
import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from tests.helpers import FIXTURES
from usf_graph import cameras as C
from usf_graph.cameras import DEFAULT_ROTATION as D
from usf_graph.cameras.rig import rig_centre

R_SCENE = 3.0  # the scene points' distance from the rig's first camera (metres)


def scene_points(n=400, seed=0):
    """Points at R_SCENE in the first camera's optical frame, all around it."""
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return R_SCENE * d / np.linalg.norm(d, axis=1, keepdims=True)


def ours(cam, P0):
    """Pixels where a rig camera stitched at R_SCENE about the first camera sees P0."""
    cam = cam.with_distance(R_SCENE)
    return cam.project(cam.to_optical(P0 @ D.T))


def check(cam, P0, T, reference, lo=0.3):
    """Compare with ``reference(points in the camera's frame)`` where the camera looks at a
    point from at least ``lo`` along its axis; T: camera <- first camera."""
    Pc = P0 @ T[:3, :3].T + T[:3, 3]
    front = Pc[:, 2] > lo * np.linalg.norm(Pc, axis=1)
    uv, ok = ours(cam, P0[front])
    ref = reference(Pc[front])
    assert ok.all() and front.sum() > 40
    np.testing.assert_allclose(uv, ref, atol=1e-6)


def rigid(rotvec, t):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rotation.from_rotvec(rotvec).as_matrix(), t
    return T


def test_a_kalibr_chain_of_three_places_each_camera_where_opencv_projects(tmp_path):
    T10 = rigid([0.1, 0.5, -0.2], [0.3, -0.1, 0.05])  # T_cn_cnm1 of cam1: cam1 <- cam0
    T21 = rigid([-0.2, 0.1, 0.3], [-0.2, 0.2, 0.1])  # cam2 <- cam1
    K, dist = [300.0, 310.0, 320.0, 240.0], [-0.1, 0.01, 0.001, -0.002]

    def cam(**kw):
        return dict(camera_model="pinhole", distortion_model="radtan", distortion_coeffs=dist,
                    intrinsics=K, resolution=[640, 480], **kw)
    path = tmp_path / "camchain.yaml"
    path.write_text(yaml.safe_dump({"cam0": cam(), "cam1": cam(T_cn_cnm1=T10.tolist()),
                                    "cam2": cam(T_cn_cnm1=T21.tolist())}))
    rig = C.load_rig(path)
    Kmat = np.array([[K[0], 0, K[2]], [0, K[1], K[3]], [0, 0, 1]])

    def opencv(Pc):
        return cv2.projectPoints(Pc, np.zeros(3), np.zeros(3), Kmat, np.array(dist))[0][:, 0]
    P0 = scene_points()
    for name, T in (("cam0", np.eye(4)), ("cam1", T10), ("cam2", T21 @ T10)):
        check(rig[name], P0, T, opencv)
    # cam2's optical centre, in the sphere frame: -R^T t of cam0 -> cam2
    T20 = T21 @ T10
    np.testing.assert_allclose(rig["cam2"].position, D @ (-T20[:3, :3].T @ T20[:3, 3]), atol=1e-12)


def test_basalt_places_its_cameras_where_opencv_projects():
    calib = json.loads((FIXTURES / "basalt_calib.json").read_text())["value0"]
    rig = C.load_rig(FIXTURES / "basalt_calib.json")

    def imu_from(i):
        p = calib["T_imu_cam"][i]
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat([p["qx"], p["qy"], p["qz"], p["qw"]]).as_matrix()
        T[:3, 3] = p["px"], p["py"], p["pz"]
        return T
    P0 = scene_points()
    for i in (1, 2):  # kb4 (cv2.fisheye) and pinhole-radtan8 (cv2.projectPoints)
        c = calib["intrinsics"][i]["intrinsics"]
        Kmat = np.array([[c["fx"], 0, c["cx"]], [0, c["fy"], c["cy"]], [0, 0, 1]])
        T = np.linalg.inv(imu_from(i)) @ imu_from(0)  # cam i <- cam0
        if i == 1:
            k = np.array([c[f"k{j}"] for j in range(1, 5)])

            def ref(Pc, Kmat=Kmat, k=k):
                return cv2.fisheye.projectPoints(Pc[:, None], np.zeros(3), np.zeros(3), Kmat, k)[0][:, 0]
        else:
            d = np.array([c[n] for n in ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")])

            def ref(Pc, Kmat=Kmat, d=d):
                return cv2.projectPoints(Pc, np.zeros(3), np.zeros(3), Kmat, d)[0][:, 0]
        check(rig[f"cam{i}"], P0, T, ref, lo=0.5)


def test_an_orbslam3_stereo_pair_places_its_right_camera_where_opencv_projects():
    path = FIXTURES / "orbslam3_stereo_kb8.yaml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    T12 = fs.getNode("Stereo.T_c1_c2").mat().astype(np.float64)  # c1 <- c2
    Kmat = np.array([[fs.getNode("Camera2.fx").real(), 0, fs.getNode("Camera2.cx").real()],
                     [0, fs.getNode("Camera2.fy").real(), fs.getNode("Camera2.cy").real()],
                     [0, 0, 1]])
    k = np.array([fs.getNode(f"Camera2.k{j}").real() for j in range(1, 5)])
    fs.release()
    rig = C.load_rig(path)
    check(rig["Camera2"], scene_points(), np.linalg.inv(T12), lambda Pc: cv2.fisheye.projectPoints(
        Pc[:, None], np.zeros(3), np.zeros(3), Kmat, k)[0][:, 0])
    # the right camera sits 0.1 m to the right: -y in the sphere frame (x forward, y left)
    np.testing.assert_allclose(rig["Camera2"].position, [0, -0.1, 0], atol=1e-7)


@pytest.mark.parametrize("where", ["colmap_rig", "colmap_rig_bin"])
def test_a_colmap_rig_places_its_cameras_where_pycolmap_projects(where):
    pycolmap = pytest.importorskip("pycolmap")
    sys.path.insert(0, str(FIXTURES))
    try:
        from make_colmap_fixture import rig_model
    finally:
        sys.path.remove(str(FIXTURES))
    model = rig_model()  # the pycolmap objects the fixture was written from
    rig = C.load_rig(FIXTURES / where)
    P0 = scene_points()
    for cid in (2, 3):
        pose = model.rigs[4].sensor_from_rig(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, cid))
        T = np.vstack([pose.matrix(), [0, 0, 0, 1]])

        def ref(Pc, cid=cid):
            # pycolmap's pixel centres sit at half integers, ours at integers
            return model.cameras[cid].img_from_cam(Pc) - 0.5
        check(rig[str(cid)], P0, T, ref, lo=0.5)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=3, max_size=3),
       st.lists(st.floats(-0.4, 0.4), min_size=3, max_size=3),
       st.floats(0.8, 50.0), st.sampled_from(["pinhole", "fisheye"]))
def test_lens_normal_map_and_sees_are_inverse_with_parallax(rotvec, position, distance, kind):
    cam = (C.Pinhole(40, 42, 23.5, 15.5, 48, 32, dist=[-0.2, 0.05, 0.001, 0.0]) if kind == "pinhole"
           else C.KannalaBrandt(14, 14, 23.5, 15.5, 48, 32, k=[0.02, -0.01, 0, 0]))
    cam = cam.with_rotation(Rotation.from_rotvec(rotvec).as_matrix() @ D)
    cam = cam.with_position(position).with_distance(distance)
    d, valid = cam.lens_normal_map()
    assert valid.sum() > 0.9 * valid.size
    np.testing.assert_allclose(np.linalg.norm(d[valid], axis=-1), 1, atol=1e-12)
    # the scene point distance * d lies on the pixel's ray from the camera's centre
    ray = cam.unproject(cam.pixel_grid())[0][valid] @ cam.rotation.T
    off = distance * d[valid] - cam.position
    np.testing.assert_allclose(off / np.linalg.norm(off, axis=-1, keepdims=True), ray, atol=1e-9)
    uv, seen = cam.sees(d[valid])
    assert seen.all()
    np.testing.assert_allclose(uv, cam.pixel_grid()[valid], atol=1e-6)


def test_far_away_the_parallax_vanishes_and_without_a_position_there_is_none():
    cam = C.KannalaBrandt(100, 100, 99.5, 99.5, 200, 200, k=[0, 0, 0, 0]).with_position([0.2, 0.1, 0])
    plain = cam.with_position(None)
    near, far = cam.with_distance(2.0), cam.with_distance(2e6)
    assert not cam.has_parallax and near.has_parallax
    a, b, c = (x.lens_normal_map()[0] for x in (plain, near, far))
    assert np.nanmax(np.abs(a - b)) > 0.05  # up to 0.2 / 2 rad of parallax
    np.testing.assert_allclose(c, a, atol=2e-7)
    # without a position a distance changes nothing; the cache key follows the rays: a
    # position without a distance shares the centred camera's geometry
    np.testing.assert_array_equal(plain.with_distance(2.0).lens_normal_map()[0], a)
    assert len({str(x.key()) for x in (plain, near, far)}) == 3 and cam.key() == plain.key()
    assert C.from_doc(cam.to_doc()).position.tolist() == [0.2, 0.1, 0.0]  # kept all the same


def test_positions_and_distances_survive_a_round_trip_and_bad_ones_are_refused(tmp_path):
    cam = C.Mei(200, 200, 159.5, 119.5, 320, 240, xi=0.8).with_position([0.1, -0.2, 0.3]).with_distance(4.0)
    cam.save(tmp_path / "cam.yaml")
    back = C.load(tmp_path / "cam.yaml")
    assert back.key() == cam.key() and repr(back) == repr(cam)
    assert ".with_position([0.1, -0.2, 0.3]).with_distance(4.0)" in repr(cam)
    with pytest.raises(ValueError, match=r"outside the scene sphere of radius 0.2; give a distance beyond"):
        cam.with_distance(0.2)
    with pytest.raises(ValueError, match="outside the scene sphere"):
        cam.with_position([5.0, 0, 0])
    with pytest.raises(ValueError, match="distance must be"):
        cam.with_distance(float("nan"))
    with pytest.raises(ValueError, match="distance must be"):
        cam.with_distance(-1.0)
    with pytest.raises(ValueError, match=r"position must be 3 numbers"):
        cam.with_position([1.0, 2.0])
    with pytest.raises(ValueError, match="position"):
        cam.with_position([np.nan, 0, 0])
    doc = cam.to_doc() | {"distance": 0.1}
    with pytest.raises(ValueError, match=r"<camera document>: .*outside the scene sphere"):
        C.from_doc(doc)


def test_stitch_at_centres_the_rig_and_says_what_is_missing():
    rig = C.load_rig(FIXTURES / "kalibr_rig.yaml")  # cam1 0.1 m behind cam0
    at = C.stitch_at(rig, 2.0)
    np.testing.assert_allclose([c.position for c in at.values()], [[0.05, 0, 0], [-0.05, 0, 0]], atol=1e-15)
    assert all(c.distance == 2.0 for c in at.values())
    at0 = C.stitch_at(rig, 2.0, centre=[0, 0, 0])
    np.testing.assert_allclose(at0["cam1"].position, [-0.1, 0, 0], atol=1e-15)
    assert all(c.distance is None for c in C.stitch_at(at, None).values())
    with pytest.raises(ValueError, match=r"the distance 0.04 does not reach past the rig: a camera is 0.05"):
        C.stitch_at(rig, 0.04)
    with pytest.raises(ValueError, match=r"\['b'\] have no position"):
        C.stitch_at({"a": rig["cam0"], "b": rig["cam1"].with_position(None)}, 2.0)
    with pytest.raises(ValueError, match="centre must be 'mean' or 3 numbers"):
        C.stitch_at(rig, 2.0, centre="middle")
    for centre in ([0.0, 0.0], [0.0, float("nan"), 0.0]):  # too few numbers; not finite
        with pytest.raises(ValueError, match="centre must be 3 finite numbers"):
            C.stitch_at(rig, 2.0, centre=centre)
    far = rig_centre(rig)[1]  # a sphere through the farthest camera is not beyond it
    with pytest.raises(ValueError, match="does not reach past the rig"):
        C.stitch_at(rig, far)
    assert C.stitch_at(rig, far * (1 + 1e-12))["cam0"].distance == far * (1 + 1e-12)


def test_turning_a_camera_apart_turns_what_it_sees():
    """``turned(R)`` turns the position with the rotation: the camera then sees direction
    R p where it saw p, parallax included; turning the rotation alone does not."""
    rng = np.random.default_rng(3)
    R = Rotation.random(random_state=4).as_matrix()
    cam = C.KannalaBrandt(60, 60, 63.5, 63.5, 128, 128, k=[0.01, 0, 0, 0]).with_fov(200)
    cam = cam.with_position([0.3, -0.2, 0.1]).with_distance(1.5)
    p = rng.normal(size=(500, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    uv, seen = cam.sees(p)
    uv_t, seen_t = cam.turned(R).sees(p @ R.T)
    assert seen.sum() > 100 and (seen == seen_t).all()
    np.testing.assert_allclose(uv_t[seen], uv[seen], atol=1e-9)
    uv_r, _ = cam.with_rotation(R @ cam.rotation).sees(p @ R.T)
    assert np.nanmax(np.abs(uv_r[seen] - uv[seen])) > 1  # pixels
