"""RosBagFrames: a bag's frames lifted once, their stamps and IMU up, the processed file."""

import numpy as np
import pytest
import torch
import yaml

from tests.helpers import FIXTURES
from usf_graph import cameras
from usf_graph.datasets import RosBagFrames
from usf_graph.frontend import SphericalFrontend

pytest.importorskip("rosbags")
from tests.test_bags import ROS2, frame, image_msg, imu_msg, messages, write_bag  # noqa: E402


@pytest.fixture
def bag(tmp_path):
    calib = FIXTURES / "ros_equidistant.yaml"
    msgs = [m for m in messages(ROS2, False, 1, calib) if m[0] == "/cam/camera_info"]
    cam = cameras.load(calib)
    for i in range(4):  # frames at the calibration's size
        big = np.resize(frame(i), (cam.height, cam.width, 3)).astype(np.uint8)
        msgs.append(("/cam/image_raw", image_msg(ROS2, big, 50 + i, 0), 1 + i))
    tilt = np.array([0.1, -0.99, 0.05])  # the camera's optical frame: up is -y, tilted
    msgs += [("/imu", imu_msg(ROS2, 9.81 * tilt, 50 + k // 10, (k % 10) * 10**8), 10 + k)
             for k in range(40)]
    return write_bag(tmp_path / "run", False, msgs), cam, tilt


def test_frames_are_lifted_once_with_their_stamps(tmp_path, bag):
    path, cam, _ = bag
    ds = RosBagFrames(tmp_path / "data", path, grid="icosahedral:3", progress=False)
    assert len(ds) == 4 and ds.topic == "/cam/image_raw" and ds.camera.key() == cam.key()
    fe = SphericalFrontend(cam, ds.grid)
    for i in range(4):
        d = ds[i]
        img = np.resize(frame(i), (cam.height, cam.width, 3)).astype(np.float32) / 255
        torch.testing.assert_close(d.x, fe.lift(img).to(torch.float16).float())
        assert torch.equal(d.mask, fe.mask) and d.stamp_ns.item() == (50 + i) * 10**9
    assert "up" not in ds[0]
    with pytest.raises(ValueError, match="made without an IMU topic"):
        _ = ds.gravity
    files = sorted((tmp_path / "data" / "processed").glob("rosbag_*.pt"))
    assert len(files) == 1
    before = files[0].stat().st_mtime_ns
    again = RosBagFrames(tmp_path / "data", path, grid="icosahedral:3", progress=False)
    assert files[0].stat().st_mtime_ns == before and torch.equal(again.x, ds.x)  # not lifted again
    half = RosBagFrames(tmp_path / "data", path, grid="icosahedral:3", every=2, progress=False)
    assert len(half) == 2 and torch.equal(half.x[1], ds.x[2])
    assert len(list((tmp_path / "data" / "processed").glob("rosbag_*.pt"))) == 2
    files[0].write_bytes(b"not a tensor file")  # a corrupt processed file is made again
    with pytest.warns(UserWarning, match="unreadable"):
        fixed = RosBagFrames(tmp_path / "data", path, grid="icosahedral:3", progress=False)
    assert torch.equal(fixed.x, ds.x)


def test_each_frame_gets_the_imus_up(tmp_path, bag):
    path, cam, tilt = bag
    chain = tmp_path / "camchain-imucam.yaml"  # the IMU in the camera's optical frame
    c = yaml.safe_load((FIXTURES / "kalibr_rig.yaml").read_text())["cam0"]
    c.update(intrinsics=[float(v) for v in (cam.fx, cam.fy, cam.cx, cam.cy)], resolution=[cam.width, cam.height],
             distortion_coeffs=[float(v) for v in cam.k], T_cam_imu=np.eye(4).tolist())
    chain.write_text(yaml.safe_dump({"cam0": c}))
    ds = RosBagFrames(tmp_path / "d", path, camera=chain, grid="icosahedral:3", imu="/imu",
                      progress=False)
    up = cameras.DEFAULT_ROTATION @ tilt / np.linalg.norm(tilt)
    assert up[2] > 0.99  # nearly level: up is the sphere frame's +z
    np.testing.assert_allclose(ds.gravity.numpy(), np.tile(up, (4, 1)), atol=1e-12)
    torch.testing.assert_close(ds[3].up, torch.as_tensor(up, dtype=torch.float32)[None])
    with pytest.raises(ValueError, match="imu needs the IMU's rotation"):
        RosBagFrames(tmp_path / "d", path, grid="icosahedral:3", imu="/imu", progress=False)
    with pytest.raises(FileNotFoundError, match="is not a ROS bag"):
        RosBagFrames(tmp_path / "d", chain, progress=False)
    with pytest.raises(ValueError, match="every must be a positive whole number"):
        RosBagFrames(tmp_path / "d", path, every=0, progress=False)


def test_the_imus_orientation_is_read_on_its_own_clock(tmp_path, bag):
    """``imu_up="orientation"``, and the calibration's ``timeshift_cam_imu`` (1 s here): the
    frame stamped 50 + i s reads the orientation the IMU gave at 51 + i s."""
    from scipy.spatial.transform import Rotation

    path, cam, _ = bag
    rot = lambda t: Rotation.from_rotvec([0.05 * int(t), 0.0, 0.0])  # noqa: E731 (world <- IMU)
    msgs = [("/imu", imu_msg(ROS2, (0.0, 0.0, 9.81), 50 + k // 10, (k % 10) * 10**8,
                             quat=rot(50 + k / 10).as_quat()), k) for k in range(60)]
    for i in range(4):
        big = np.resize(frame(i), (cam.height, cam.width, 3)).astype(np.uint8)
        msgs.append(("/cam/image_raw", image_msg(ROS2, big, 50 + i, 0), 100 + i))
    imu_bag = write_bag(tmp_path / "imu", False, msgs)
    chain = tmp_path / "camchain-imucam.yaml"
    c = yaml.safe_load((FIXTURES / "kalibr_rig.yaml").read_text())["cam0"]
    c.update(intrinsics=[float(v) for v in (cam.fx, cam.fy, cam.cx, cam.cy)],
             resolution=[cam.width, cam.height], distortion_coeffs=[float(v) for v in cam.k],
             T_cam_imu=np.eye(4).tolist(), timeshift_cam_imu=1.0)
    chain.write_text(yaml.safe_dump({"cam0": c}))
    ds = RosBagFrames(tmp_path / "d", imu_bag, camera=chain, grid="icosahedral:3", imu="/imu",
                      imu_up="orientation", progress=False)
    assert ds.imu_time_shift_ns == 10**9
    want = [cameras.DEFAULT_ROTATION @ rot(51 + i).inv().apply([0.0, 0.0, 1.0]) for i in range(4)]
    np.testing.assert_allclose(ds.gravity.numpy(), want, atol=1e-12)
    same = RosBagFrames(tmp_path / "d", imu_bag, camera=chain, grid="icosahedral:3", imu="/imu",
                        imu_up="orientation", imu_time_shift_ns=0, progress=False)
    np.testing.assert_allclose(same.gravity.numpy()[1:], want[:3], atol=1e-12)  # its own file
    with pytest.raises(ValueError, match="imu_up must be 'accel' or 'orientation'"):
        RosBagFrames(tmp_path / "d", imu_bag, camera=chain, imu="/imu", imu_up="gyro")


def test_a_mono_camera_with_a_camera_object_and_its_imu_rotation(tmp_path, bag):
    """Mono frames lift to one channel; with a Camera (no calibration file) the IMU's
    rotation is given, and the IMU's clock is the frames' own."""
    path, cam, tilt = bag
    msgs = [("/imu", imu_msg(ROS2, 9.81 * tilt, 50 + k // 10, (k % 10) * 10**8), k) for k in range(40)]
    grays = [np.resize(frame(i)[..., 1], (cam.height, cam.width)).astype(np.uint8) for i in range(2)]
    msgs += [("/mono", image_msg(ROS2, g, 50 + i, 0), 50 + i) for i, g in enumerate(grays)]
    R = cameras.DEFAULT_ROTATION
    ds = RosBagFrames(tmp_path / "d", write_bag(tmp_path / "mono", False, msgs), camera=cam,
                      grid="icosahedral:3", imu="/imu", imu_to_sphere=R, progress=False)
    assert ds.imu_time_shift_ns == 0 and ds.topic == "/mono"
    np.testing.assert_allclose(ds.gravity.numpy(), np.tile(R @ tilt / np.linalg.norm(tilt), (2, 1)),
                               atol=1e-12)
    fe = SphericalFrontend(cam, ds.grid)
    for d, g in zip(ds, grays):
        assert d.x.shape == (642, 1)
        torch.testing.assert_close(d.x, fe.lift(g.astype(np.float32) / 255).to(torch.float16).float())


def test_png_frames_with_alpha_lift_their_colour(tmp_path):
    """A compressed topic's PNGs may carry alpha: the colour is lifted, the alpha dropped
    (the camera's mask says what it sees)."""
    import cv2

    from tests.test_bags import ROS2

    cam = cameras.load(FIXTURES / "ros_equidistant.yaml")
    T = ROS2.types
    msgs, want = [], []
    for i in range(2):
        rgb = np.resize(frame(i), (cam.height, cam.width, 3)).astype(np.uint8)
        alpha = np.full(rgb.shape[:2] + (1,), 40 + 100 * i, np.uint8)
        png = cv2.imencode(".png", np.concatenate([rgb[..., ::-1], alpha], -1))[1].reshape(-1)
        h = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=5 + i, nanosec=0),
                                     frame_id="cam")
        msgs.append(("/cam/image_raw/compressed", T["sensor_msgs/msg/CompressedImage"](
            header=h, format="png", data=png), 1 + i))
        want.append(rgb)
    ds = RosBagFrames(tmp_path / "data", write_bag(tmp_path / "rgba", False, msgs), camera=cam,
                      grid="icosahedral:3", progress=False)
    fe = SphericalFrontend(cam, ds.grid)
    for d, rgb in zip(ds, want):
        assert d.x.shape == (642, 3)
        torch.testing.assert_close(d.x, fe.lift(rgb.astype(np.float32) / 255).to(torch.float16).float())
