"""ROS bags: frames and camera_info read from bags that rosbags' own writers make, ROS 1 and
ROS 2, and the errors for what cannot be read."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from tests.helpers import FIXTURES, tiny_seg_checkpoint
from usf_graph import bags, cameras

pytest.importorskip("rosbags")
pytest.importorskip("rosbags.image")
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

ROS2, ROS1 = get_typestore(Stores.ROS2_HUMBLE), get_typestore(Stores.ROS1_NOETIC)


def frame(i, h=48, w=64):
    """An RGB frame that differs per i and in every channel."""
    y, x = np.mgrid[:h, :w]
    return np.stack([(x * 4 + i) % 256, (y * 5 + 3 * i) % 256, (x + y + 7 * i) % 256], -1).astype(np.uint8)


def info_fields(calib: Path) -> dict:
    """A ROS camera_info YAML file's values, as a CameraInfo message has them."""
    c = yaml.safe_load(calib.read_text())
    return dict(width=c["image_width"], height=c["image_height"], model=c["distortion_model"],
                k=np.array(c["camera_matrix"]["data"], float),
                d=np.array(c["distortion_coefficients"]["data"], float))


def messages(ts, ros1: bool, n, calib=None, encoding="rgb8", k_zero=False, binning=0):
    """(topic, msgtype, message, time) of n raw frames, n PNG frames and a camera_info."""
    T = ts.types
    stamp = lambda i: T["builtin_interfaces/msg/Time"](sec=100 + i, nanosec=5)  # noqa: E731
    header = (lambda i: T["std_msgs/msg/Header"](seq=i, stamp=stamp(i), frame_id="cam")) if ros1 \
        else (lambda i: T["std_msgs/msg/Header"](stamp=stamp(i), frame_id="cam"))
    out = []
    for i in range(n):
        rgb = frame(i)
        data = {"rgb8": rgb, "bgr8": rgb[..., ::-1], "mono8": rgb[..., 0]}[encoding]
        img = T["sensor_msgs/msg/Image"](header=header(i), height=48, width=64, encoding=encoding,
                                         is_bigendian=0, step=data[0].size,
                                         data=np.ascontiguousarray(data).reshape(-1))
        png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))[1].reshape(-1)
        comp = T["sensor_msgs/msg/CompressedImage"](header=header(i), format="png", data=png)
        out += [("/cam/image_raw", img, i), ("/cam/image_raw/compressed", comp, i)]
    if calib is not None:
        f = info_fields(calib)
        K, D, R, P = (("K", "D", "R", "P") if ros1 else ("k", "d", "r", "p"))
        roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                    do_rectify=False)
        info = T["sensor_msgs/msg/CameraInfo"](**{
            "header": header(0), "height": f["height"], "width": f["width"],
            "distortion_model": f["model"], D: f["d"], K: 0 * f["k"] if k_zero else f["k"],
            R: np.eye(3).ravel(), P: np.zeros(12), "binning_x": binning, "binning_y": binning,
            "roi": roi})
        out.append(("/cam/camera_info", info, 0))
    return out


def write_bag(path: Path, ros1: bool, msgs, mcap: bool = False) -> Path:
    """A bag of ``msgs`` written by rosbags: ROS 1, or ROS 2 in SQLite (or ``mcap``)."""
    ts = ROS1 if ros1 else ROS2
    store = StoragePlugin.MCAP if mcap else StoragePlugin.SQLITE3
    with (Writer1(path) if ros1 else Writer2(path, version=9, storage_plugin=store)) as w:
        conns = {}
        for topic, msg, i in msgs:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msg.__msgtype__, typestore=ts)
            raw = ts.serialize_ros1(msg, msg.__msgtype__) if ros1 else ts.serialize_cdr(msg, msg.__msgtype__)
            w.write(conns[topic], 10**9 * (200 + i), raw)
    return path


@pytest.mark.parametrize("ros1, mcap", [(False, False), (False, True), (True, False)],
                         ids=["ros2-sqlite", "ros2-mcap", "ros1"])
def test_frames_and_the_camera_come_back_as_written(tmp_path, ros1, mcap):
    calib = FIXTURES / "ros_equidistant.yaml"
    ts = ROS1 if ros1 else ROS2
    bag = write_bag(tmp_path / ("run.bag" if ros1 else "run"), ros1, messages(ts, ros1, 5, calib), mcap)
    assert bags.is_bag(bag) and not bags.is_bag(calib)
    if not ros1:  # a ROS 2 bag by its storage file too
        store = next(bag.glob("*.mcap" if mcap else "*.db3"))
        assert bags.is_bag(store) and bags.topics(store) == bags.topics(bag)
    assert bags.topics(bag)["/cam/image_raw"] == ("sensor_msgs/msg/Image", 5)
    got = list(bags.frames(bag, "/cam/image_raw"))
    assert [f.index for f in got] == list(range(5))
    assert [f.stamp_ns for f in got] == [(100 + i) * 10**9 + 5 for i in range(5)]  # the header's
    for f in got:
        np.testing.assert_array_equal(f.image, frame(f.index))
    png = list(bags.frames(bag, "/cam/image_raw/compressed", every=2))
    assert [f.index for f in png] == [0, 2, 4] and all(f.topic == "/cam/image_raw/compressed" for f in png)
    for f in png:
        np.testing.assert_array_equal(f.image, frame(f.index))
    # the camera_info beside either topic is the one the ROS YAML file holds
    for topic in ("/cam/image_raw", "/cam/image_raw/compressed"):
        assert bags.camera(bag, topic).key() == cameras.load(calib).key()


@pytest.mark.parametrize("ros1", [False, True], ids=["ros2", "ros1"])
def test_encodings_read_as_rgb_or_mono_and_pinholes_as_pinholes(tmp_path, ros1):
    ts = ROS1 if ros1 else ROS2
    calib = FIXTURES / "ros_plumb_bob.yaml"
    for enc in ("bgr8", "mono8"):
        msgs = [m for m in messages(ts, ros1, 2, calib, encoding=enc) if "compressed" not in m[0]]
        bag = write_bag(tmp_path / f"{enc}{'.bag' if ros1 else ''}", ros1, msgs)
        f = next(bags.frames(bag))  # the only image topic
        want = frame(0)[..., 0] if enc == "mono8" else frame(0)  # bgr8 turned to RGB
        np.testing.assert_array_equal(f.image, want)
        cam = bags.camera(bag)
        assert isinstance(cam, cameras.Pinhole) and cam.key() == cameras.load(calib).key()


def test_the_bag_command_lists_what_predict_reads(tmp_path, capsys):
    from usf_graph.cli import main

    msgs = messages(ROS2, False, 2, FIXTURES / "ros_equidistant.yaml")
    msgs += [("/imu0", imu_msg(ROS2, (0.0, 0.0, 9.81), 100, 0), 3),
             ("/left/image_raw", image_msg(ROS2, frame(0), 100, 0), 4),
             ("/note", ROS2.types["std_msgs/msg/String"](data="hi"), 5)]
    bag = write_bag(tmp_path / "run", False, msgs)
    assert main(["bag", str(bag)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[-1] == "other topics: /cam/camera_info (CameraInfo), /note (String)"
    assert lines[1].split() == ["/cam/image_raw", "Image", "2", "/cam/camera_info"]
    assert lines[2].split() == ["/cam/image_raw/compressed", "CompressedImage", "2", "/cam/camera_info"]
    assert lines[3].split()[:4] == ["/left/image_raw", "Image", "1", "-"]  # no /left/camera_info
    assert lines[4] == "IMU /imu0 (1 messages): predict --imu /imu0"
    assert main(["bag", str(tmp_path / "none")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["lift", str(bag), "--camera", str(FIXTURES / "ros_equidistant.yaml")]) == 2
    assert "is a ROS bag, not an image: 'usf-graph predict' reads bags" in capsys.readouterr().err
    # one camera's images and a camera_info not beside them: that camera_info
    info = [m for m in msgs if m[0] == "/cam/camera_info"][0][1]
    odd = write_bag(tmp_path / "odd", False, [("/front/image_raw", image_msg(ROS2, frame(0), 100, 0), 0),
                                              ("/calib/info", info, 1)])
    assert bags.camera(odd).key() == cameras.load(FIXTURES / "ros_equidistant.yaml").key()


def test_what_cannot_be_read_says_why(tmp_path):
    calib = FIXTURES / "ros_equidistant.yaml"
    bag = write_bag(tmp_path / "two", False, messages(ROS2, False, 1))
    with pytest.raises(ValueError, match=r"has 2 image topics \(/cam/image_raw, "
                                         r"/cam/image_raw/compressed\); choose one with --topic"):
        next(bags.frames(bag))
    with pytest.raises(ValueError, match=r"no image topic '/cam/left'; its image topics: /cam/image_raw"):
        next(bags.frames(bag, "/cam/left"))
    with pytest.raises(ValueError, match=r"no camera_info for /cam/image_raw \(looked for "
                                         r"/cam/camera_info; the bag's: none\); give the calibration"):
        bags.camera(bag, "/cam/image_raw")
    zero = write_bag(tmp_path / "zero", False, messages(ROS2, False, 1, calib, k_zero=True))
    with pytest.raises(ValueError, match=r"\[/cam/camera_info\]: the camera_info is uncalibrated"):
        bags.camera(zero, "/cam/image_raw")
    one, none = (write_bag(tmp_path / f"b{b}", False, messages(ROS2, False, 1, calib, binning=b)) for b in (1, 0))
    assert bags.camera(one, "/cam/image_raw").key() == bags.camera(none, "/cam/image_raw").key()  # 1: not binned
    binned = write_bag(tmp_path / "binned", False, messages(ROS2, False, 1, calib, binning=2))
    with pytest.raises(ValueError, match=r"binned or cropped camera_info \(binning 2x2"):
        bags.camera(binned, "/cam/image_raw")
    (tmp_path / "junk.bag").write_bytes(b"#ROSBAG V2.0\n" + bytes(100))
    with pytest.raises(ValueError, match=r"cannot read ROS bag .*junk.bag"):
        bags.topics(tmp_path / "junk.bag")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        bags.topics(tmp_path / "missing.bag")


def test_predict_reads_a_bag_and_its_camera_info(tmp_path, capsys):
    """``predict seg CKPT run/ --topic ...`` gives every frame the labels that predicting
    its PNG with the calibration file gives."""
    from usf_graph.cli import main

    calib = FIXTURES / "ros_equidistant.yaml"
    f = info_fields(calib)
    cam = cameras.load(calib)
    # frames at the calibration's size: a scaled version of the test frame
    msgs = []
    for topic, msg, i in messages(ROS2, False, 3, calib):
        if topic == "/cam/image_raw":
            big = cv2.resize(frame(i), (f["width"], f["height"]), interpolation=cv2.INTER_NEAREST)
            msg = type(msg)(header=msg.header, height=f["height"], width=f["width"], encoding="rgb8",
                            is_bigendian=0, step=3 * f["width"], data=big.reshape(-1))
            cv2.imwrite(str(tmp_path / f"frame{i}.png"), cv2.cvtColor(big, cv2.COLOR_RGB2BGR))
        if "compressed" not in topic:
            msgs.append((topic, msg, i))
    bag = write_bag(tmp_path / "run", False, msgs)
    tiny_seg_checkpoint(tmp_path / "seg.pt")
    ckpt = str(tmp_path / "seg.pt")
    assert main(["predict", "seg", ckpt, str(bag), "--every", "2", "--out", str(tmp_path / "b"),
                 "--video", str(tmp_path / "b" / "run.avi")]) == 0
    out = capsys.readouterr().out
    assert f"wrote {tmp_path / 'b' / 'run.avi'} (2 frames at 10 fps)" in out
    cap = cv2.VideoCapture(str(tmp_path / "b" / "run.avi"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 2
    ok, first = cap.read()
    cap.release()
    assert ok and first.shape == (f["height"], 2 * f["width"], 3)  # the image beside its labels
    assert f"camera from {bag}'s camera_info: {cam}" in out and "run#/cam/image_raw@101000000005" not in out
    assert f"== {bag}#/cam/image_raw@100000000005" in out and f"== {bag}#/cam/image_raw@102000000005" in out
    assert main(["predict", "seg", ckpt, str(bag), "--topic", "/cam/image_raw", "--every", "2",
                 "--out", str(tmp_path / "t")]) == 0  # the topic named, its camera_info found
    assert main(["predict", "seg", ckpt, str(tmp_path / "frame0.png"), str(tmp_path / "frame2.png"),
                 "--camera", str(calib), "--out", str(tmp_path / "p")]) == 0
    for i in (0, 2):
        a = cv2.imread(str(tmp_path / "b" / f"run_{i:06d}_labels.png"), cv2.IMREAD_UNCHANGED)
        b = cv2.imread(str(tmp_path / "p" / f"frame{i}_labels.png"), cv2.IMREAD_UNCHANGED)
        assert a is not None and np.array_equal(a, b)
        t = cv2.imread(str(tmp_path / "t" / f"run_{i:06d}_labels.png"), cv2.IMREAD_UNCHANGED)
        assert np.array_equal(t, b)
    assert not (tmp_path / "b" / "run_000001_labels.png").exists()
    capsys.readouterr()
    for argv, msg in (([str(tmp_path / "frame0.png")], "give the camera's calibration with --camera"),
                      ([str(tmp_path / "frame0.png"), "--camera", str(calib), "--topic", "/x"],
                       "--topic picks a ROS bag's image topic; no bag"),
                      ([str(bag), "--key", "cam1"], "--key picks a camera in --camera's file"),
                      ([str(bag), str(tmp_path / "frame0.png"), "--rig", "--camera", str(calib)],
                       "nor bags among images"),
                      ([str(bag), "--rig", "--camera", str(calib)], "a rig is read from"),
                      ([str(bag), "--topic", "/cam/left"], "no image topic '/cam/left'")):
        assert main(["predict", "seg", ckpt, *argv]) == 2, argv
        assert msg in capsys.readouterr().err


def image_msg(ts, rgb, sec, nanosec):
    T = ts.types
    h = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
                                 frame_id="cam")
    mono = rgb.ndim == 2  # a mono camera's frame
    return T["sensor_msgs/msg/Image"](header=h, height=rgb.shape[0], width=rgb.shape[1],
                                      encoding="mono8" if mono else "rgb8", is_bigendian=0,
                                      step=(1 if mono else 3) * rgb.shape[1],
                                      data=np.ascontiguousarray(rgb).reshape(-1))


def test_a_rig_bag_gives_frames_matched_by_stamp(tmp_path):
    # front at 0, 0.1, 0.2, 0.3 s; back 3 ms late, but 50 ms late for frame 2 and none for 3
    msgs = []
    for i in range(4):
        msgs.append(("/front", image_msg(ROS2, frame(i), 10, i * 10**8), 2 * i))
        if i < 3:
            late = 50 if i == 2 else 3
            msgs.append(("/back", image_msg(ROS2, frame(10 + i), 10, i * 10**8 + late * 10**6), 2 * i + 1))
    bag = write_bag(tmp_path / "rig", False, msgs)
    with pytest.warns(UserWarning, match=r"2 of the 4 frames of /front have no image of every other camera within 10 ms"):
        got = list(bags.rig_frames(bag, ["/front", "/back"]))
    assert [f.index for f in got] == [0, 1]
    assert got[1].stamps_ns == (10 * 10**9 + 10**8, 10 * 10**9 + 10**8 + 3 * 10**6)
    for f in got:
        np.testing.assert_array_equal(f.images[0], frame(f.index))
        np.testing.assert_array_equal(f.images[1], frame(10 + f.index))
    wide = list(bags.rig_frames(bag, ["/front", "/back"], every=2, max_skew_ns=60 * 10**6))
    assert [f.index for f in wide] == [0, 2]
    np.testing.assert_array_equal(wide[1].images[1], frame(12))
    with pytest.raises(ValueError, match="one topic each"):
        next(bags.rig_frames(bag, ["/front", "/front"]))
    with pytest.raises(ValueError, match=r"no frame of /back has an image of every other camera \(/front\) within 0.001 ms"):
        next(bags.rig_frames(bag, ["/back", "/front"], max_skew_ns=1000))
    # a frame's index is the first topic's message index, though /back has one more before
    msgs = [("/back", image_msg(ROS2, frame(9), 9, 0), 0)]
    for i in range(3):
        msgs += [("/front", image_msg(ROS2, frame(i), 10, i * 10**8), 2 * i + 1),
                 ("/back", image_msg(ROS2, frame(10 + i), 10, i * 10**8 + 10**6), 2 * i + 2)]
    early = list(bags.rig_frames(write_bag(tmp_path / "early", False, msgs), ["/front", "/back"]))
    assert [f.index for f in early] == [0, 1, 2]
    assert all(np.array_equal(f.images[1], frame(10 + f.index)) for f in early)


def test_predict_on_a_kalibr_rig_bag_reads_the_camchain_topics(tmp_path, capsys):
    """``predict seg CKPT rig_bag --rig --camera camchain``: the camchain's rostopics, one
    sphere per frame, the labels that the frames' PNGs give with ``--rig``."""
    from usf_graph.cli import main
    from usf_graph.frontend import render
    from usf_graph.viz import labelled_panorama

    chain = FIXTURES / "kalibr_rig.yaml"
    rig = {n: c.with_fov(190) for n, c in cameras.load_rig(chain).items()}
    msgs = []
    for i, shift in enumerate((0, 40)):
        pano = np.roll(labelled_panorama(256, 128), shift, axis=1)
        for k, (name, cam) in enumerate(rig.items()):
            im = (255 * render(pano, cameras.Equirectangular(256, 128), cam)).round().astype(np.uint8)
            cv2.imwrite(str(tmp_path / f"f{i}_{name}.png"), cv2.cvtColor(im, cv2.COLOR_RGB2BGR))
            topic = cameras.rig_topics(chain)[k]
            msgs.append((topic, image_msg(ROS2, im, 5 + i, k * 10**6), 2 * i + k))
    bag = write_bag(tmp_path / "drive", False, msgs)
    tiny_seg_checkpoint(tmp_path / "seg.pt")
    ckpt = str(tmp_path / "seg.pt")
    common = ["--camera", str(chain), "--fov", "190", "--rig"]
    assert main(["predict", "seg", ckpt, str(bag), *common, "--out", str(tmp_path / "b"),
                 "--video", str(tmp_path / "drive.mp4"), "--video-fps", "5"]) == 0
    out = capsys.readouterr().out
    assert "rig cam0 <- /front/image_raw, cam1 <- /back/image_raw" in out
    assert "(2 frames at 5 fps)" in out
    cap = cv2.VideoCapture(str(tmp_path / "drive.mp4"))
    ok, first = cap.read()
    assert ok and first.shape == (800, 800, 3) and cap.get(cv2.CAP_PROP_FPS) == 5  # cameras stacked
    cap.release()
    for i in (0, 1):
        assert main(["predict", "seg", ckpt, str(tmp_path / f"f{i}_cam0.png"),
                     str(tmp_path / f"f{i}_cam1.png"), *common, "--out", str(tmp_path / "p")]) == 0
        for name in rig:
            a = cv2.imread(str(tmp_path / "b" / f"drive_{name}_{i:06d}_labels.png"), cv2.IMREAD_UNCHANGED)
            b = cv2.imread(str(tmp_path / "p" / f"f{i}_{name}_labels.png"), cv2.IMREAD_UNCHANGED)
            assert a is not None and np.array_equal(a, b)
    capsys.readouterr()
    # --distance auto: chosen once, on the first frame (the views are of a panorama: far away)
    assert main(["predict", "seg", ckpt, str(bag), *common, "--distance", "auto",
                 "--out", str(tmp_path / "auto")]) == 0
    assert capsys.readouterr().out.count("stitching distance chosen where the cameras agree best: ") == 1
    assert (tmp_path / "auto" / "drive_cam1_000001_labels.png").is_file()
    # frames recorded at half size: the calibrations are fitted to them, as for image files
    small = [(t, image_msg(ROS2, cv2.resize(m.data.reshape(m.height, m.width, 3), (200, 200),
                                            interpolation=cv2.INTER_AREA), 5, 0), n)
             for t, m, n in msgs[:2]]
    for k, (_, m, _) in enumerate(small):
        cv2.imwrite(str(tmp_path / f"half_{k}.png"),
                    cv2.cvtColor(m.data.reshape(200, 200, 3), cv2.COLOR_RGB2BGR))
    assert main(["predict", "seg", ckpt, str(write_bag(tmp_path / "small", False, small)),
                 *common, "--out", str(tmp_path / "s")]) == 0
    assert capsys.readouterr().out.count("scaling the calibration by 0.5") == 2
    assert main(["predict", "seg", ckpt, str(tmp_path / "half_0.png"), str(tmp_path / "half_1.png"),
                 *common, "--out", str(tmp_path / "s")]) == 0
    for k, name in enumerate(rig):
        a = cv2.imread(str(tmp_path / "s" / f"small_{name}_000000_labels.png"), cv2.IMREAD_UNCHANGED)
        b = cv2.imread(str(tmp_path / "s" / f"half_{k}_labels.png"), cv2.IMREAD_UNCHANGED)
        assert a.shape == (200, 200) and np.array_equal(a, b)
    assert main(["predict", "seg", ckpt, str(bag), *common, "--max-skew", "0.9",
                 "--out", str(tmp_path / "skew")]) == 2  # 1 ms apart: nothing written anywhere
    assert "(/back/image_raw) within 0.9 ms" in capsys.readouterr().err
    assert main(["predict", "seg", ckpt, str(bag), *common, "--topic", "/front/image_raw"]) == 2
    assert "has 2 cameras (cam0, cam1) but 1 topics" in capsys.readouterr().err
    assert main(["predict", "seg", ckpt, str(bag), "--camera", str(FIXTURES / "basalt_calib.json"),
                 "--rig"]) == 2
    assert "give each camera's image topic with --topic" in capsys.readouterr().err
    assert main(["predict", "seg", ckpt, str(bag), "--topic", "/a", "--topic", "/b"]) == 2
    assert "several --topic are a rig's cameras (--rig)" in capsys.readouterr().err


def test_render_turns_a_bags_frames_into_a_video(tmp_path, capsys):
    """``render BAG``: one topic through its camera_info, or a rig's topics (the camchain's
    rostopics) matched by stamp and stitched: each frame of the video is what a Reimager
    (a RigReimager) gives the bag's frame, at the rate of the bag's stamps."""
    from tests.frontend.test_rig import scene
    from tests.helpers import decode_video
    from usf_graph.cli import main
    from usf_graph.frontend import Reimager, RigReimager, render

    calib = FIXTURES / "ros_equidistant.yaml"
    cam = cameras.load(calib)
    msgs = [(t, m, i) for t, m, i in messages(ROS2, False, 3, calib) if t == "/cam/camera_info"]
    shots = []
    for i in range(3):  # 4 frames a second
        shots.append(cv2.resize(frame(i), (cam.width, cam.height), interpolation=cv2.INTER_CUBIC))
        msgs.append(("/cam/image_raw", image_msg(ROS2, shots[-1], 100, i * 250_000_000), i + 1))
    bag = write_bag(tmp_path / "run", False, msgs)
    pano = cameras.Equirectangular(128, 64)
    assert main(["render", str(bag), "--to", "equirectangular:128x64", "--out", str(tmp_path / "p.avi")]) == 0
    assert "camera from" in capsys.readouterr().out
    got, fps = decode_video(tmp_path / "p.avi")
    r = Reimager(cam, pano)
    assert len(got) == 3 and fps == 4
    for g, shot in zip(got, shots):
        assert np.abs(g.astype(float) - r(shot)).mean() < 3  # Motion JPEG
    assert main(["render", str(bag), "--every", "3", "--to", "equirectangular:128x64",
                 "--out", str(tmp_path / "one.avi")]) == 0  # one frame: no rate to read
    assert "gives no frame rate: writing 30 fps" in capsys.readouterr().out
    got, fps = decode_video(tmp_path / "one.avi")
    assert len(got) == 1 and fps == 30
    # a rig's bag: the camchain's topics, matched by stamp, stitched
    chain = FIXTURES / "kalibr_rig.yaml"
    rig = {n: c.with_fov(190) for n, c in cameras.load_rig(chain).items()}
    msgs, views = [], []
    smooth = scene(cameras.Equirectangular(256, 128).lens_normal_map()[0])  # JPEG keeps it
    for i, shift in enumerate((0, 40)):
        world = np.roll(smooth, shift, axis=1)
        views.append([(255 * render(world, cameras.Equirectangular(256, 128), c)).round().astype(np.uint8)
                      for c in rig.values()])
        for k, im in enumerate(views[-1]):
            msgs.append((cameras.rig_topics(chain)[k], image_msg(ROS2, im, 5 + i, k * 10**6), 2 * i + k))
    bag = write_bag(tmp_path / "drive", False, msgs)
    assert main(["render", str(bag), "--camera", str(chain), "--fov", "190", "--to",
                 "equirectangular:256x128", "--out", str(tmp_path / "r.avi")]) == 0
    assert "rig of 2 (cam0, cam1)" in capsys.readouterr().out
    got, fps = decode_video(tmp_path / "r.avi")
    stitch = RigReimager(rig, cameras.Equirectangular(256, 128))
    assert len(got) == 2 and fps == 1  # stamps 1 s apart
    for g, v in zip(got, views):
        assert np.abs(g.astype(float) - stitch(v)).mean() < 2  # Motion JPEG
    assert np.abs(got[0].astype(float) - got[1]).mean() > 10  # the world turned
    assert main(["render", str(bag), "--camera", str(chain), "--max-skew", "0.5", "--to",
                 "equirectangular:64x32", "--out", str(tmp_path / "x.avi")]) == 2  # 1 ms apart
    assert "(/back/image_raw) within 0.5 ms" in capsys.readouterr().err
    quiet = tmp_path / "quiet"  # its camera_info, and an image topic without a message
    with Writer2(quiet, version=9, storage_plugin=StoragePlugin.SQLITE3) as w:
        info = next(m for t, m, _ in messages(ROS2, False, 1, calib) if t == "/cam/camera_info")
        w.write(w.add_connection("/cam/camera_info", info.__msgtype__, typestore=ROS2), 10**9,
                ROS2.serialize_cdr(info, info.__msgtype__))
        w.add_connection("/cam/image_raw", "sensor_msgs/msg/Image", typestore=ROS2)
    for argv, why in (([str(bag), str(bag)], "give one ROS bag"),
                      ([str(quiet)], "gave no frame to re-image (with --every 1); check the topic with"),
                      ([str(tmp_path / "x.png"), "--topic", "/a"], "no bag was given"),
                      ([str(tmp_path / "x.png")], "give the camera's calibration")):
        assert main(["render", *argv, "--to", "equirectangular:64x32", "--out", str(tmp_path / "x.avi")]) == 2
        assert why in capsys.readouterr().err


def given_up(up) -> str:
    """How ``predict`` says it read ``up`` (from the IMU: given, not estimated)."""
    return "up: (" + ", ".join(f"{v:+.3f}" for v in up) + "), given"


def imu_msg(ts, acc, sec, nanosec, quat=(0.0, 0.0, 0.0, 1.0), no_orientation=False):
    """An Imu message; ``quat`` (x, y, z, w) its orientation, ``no_orientation`` marks it
    unknown (``orientation_covariance[0] = -1``)."""
    T = ts.types
    v3 = T["geometry_msgs/msg/Vector3"]
    h = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
                                 frame_id="imu")
    cov = np.zeros(9)
    cov[0] = -1.0 if no_orientation else 0.0
    return T["sensor_msgs/msg/Imu"](
        header=h, orientation=T["geometry_msgs/msg/Quaternion"](
            **dict(zip("xyzw", map(float, quat)))),
        orientation_covariance=cov, angular_velocity=v3(x=0.0, y=0.0, z=0.0),
        angular_velocity_covariance=np.zeros(9), linear_acceleration=v3(x=acc[0], y=acc[1], z=acc[2]),
        linear_acceleration_covariance=np.zeros(9))


def test_the_accelerometer_gives_up_about_each_stamp(tmp_path):
    rng = np.random.default_rng(0)
    up = np.array([0.3, -0.2, 0.93])
    up /= np.linalg.norm(up)
    msgs = [("/imu", imu_msg(ROS2, 9.81 * up + rng.normal(0, 0.05, 3), 7, i * 5 * 10**6), i)
            for i in range(100)]  # 200 Hz for 0.5 s
    msgs.append(("/imu", imu_msg(ROS2, (0.0, 0.0, 0.05), 9, 0), 100))  # falling at 9 s
    bag = write_bag(tmp_path / "imu", False, msgs)
    acc = bags.Accelerometer(bag, "/imu")
    assert len(acc.stamps) == 101
    u = acc.up(7 * 10**9 + 2 * 10**8)
    assert np.degrees(np.arccos(np.clip(u @ up, -1, 1))) < 0.5 and abs(np.linalg.norm(u) - 1) < 1e-12
    # the mean over the window: readings 30..50 (150 to 250 ms, at 5 ms each)
    want = np.mean([m[1].linear_acceleration.x for m in msgs[30:51]])
    assert u[0] == pytest.approx(want / np.linalg.norm(acc.readings[30:51].mean(0)), rel=1e-12)
    # past the last reading but within the window: the nearest
    for late in (9 * 10**7, 10**8):  # the window's whole width away still counts
        np.testing.assert_allclose(acc.up(7 * 10**9 + 495 * 10**6 + late),
                                   acc.readings[99] / np.linalg.norm(acc.readings[99]))
    with pytest.raises(ValueError, match=r"no IMU reading within 100 ms of the frame at 8000000000 ns"):
        acc.up(8 * 10**9)
    with pytest.raises(ValueError, match=r"reads 0.05 m/s\^2 about 9000000000 ns, too little to tell up"):
        acc.up(9 * 10**9)
    with pytest.raises(ValueError, match=r"no sensor_msgs/Imu topic '/imu0'; its IMU topics: /imu"):
        bags.Accelerometer(bag, "/imu0")


def test_imu_extrinsics_of_every_format_turn_the_reading_to_up(tmp_path):
    """A level camera (its sphere frame the world's) with an IMU turned by Q: at rest the
    IMU reads Q^T (0, 0, g) in its frame; each file's extrinsics, written as the format
    defines them, must turn that back to +z."""
    from scipy.spatial.transform import Rotation

    D = cameras.DEFAULT_ROTATION
    R_imu_cam = Rotation.from_rotvec([0.4, -1.1, 0.7]).as_matrix()  # IMU <- camera
    reading = R_imu_cam @ D.T @ [0, 0, 9.81]  # world (= sphere) -> camera -> IMU
    T_cam_imu = np.eye(4)
    T_cam_imu[:3, :3], T_cam_imu[:3, 3] = R_imu_cam.T, [0.01, 0.02, 0.03]
    T_imu_cam = np.linalg.inv(T_cam_imu)
    cam = dict(camera_model="pinhole", distortion_model="none", distortion_coeffs=[],
               intrinsics=[100.0, 100.0, 63.5, 47.5], resolution=[128, 96])
    kalibr = tmp_path / "camchain-imucam.yaml"
    kalibr.write_text(yaml.safe_dump({"cam0": {**cam, "T_cam_imu": T_cam_imu.tolist()}}))
    q = Rotation.from_matrix(T_imu_cam[:3, :3]).as_quat()  # x, y, z, w
    calib = yaml.safe_load((FIXTURES / "basalt_calib.json").read_text())
    calib["value0"]["T_imu_cam"][0] = dict(zip(("px", "py", "pz"), T_imu_cam[:3, 3])) | dict(
        zip(("qx", "qy", "qz", "qw"), q))
    basalt = tmp_path / "calibration.json"
    basalt.write_text(json.dumps(calib))
    text = (FIXTURES / "orbslam3_stereo_kb8.yaml").read_text()
    block = ("IMU.T_b_c1: !!opencv-matrix\n  rows: 4\n  cols: 4\n  dt: f\n  data: ["
             + ", ".join(repr(float(v)) for v in T_imu_cam.ravel()) + "]\n")
    orb = tmp_path / "orbslam.yaml"
    orb.write_text(text + "\n" + block)
    for path in (kalibr, basalt, orb):
        up = cameras.imu_rotation(path) @ reading
        np.testing.assert_allclose(up / 9.81, [0, 0, 1], atol=1e-6, err_msg=str(path))
    # EuRoC's camchain-imucam: its IMU's x axis points up, cam0 looks level and upright
    up = cameras.imu_rotation(FIXTURES / "kalibr_camchain.yaml") @ [1.0, 0, 0]
    assert up[2] > 0.999
    for name in ("kalibr_rig.yaml", "orbslam3_mono_pinhole.yaml"):
        with pytest.raises(ValueError, match="no camera-IMU extrinsics"):
            cameras.imu_rotation(FIXTURES / name)


def test_predict_with_imu_up_matches_the_same_up_given(tmp_path, capsys):
    from usf_graph.cli import main

    chain = tmp_path / "camchain-imucam.yaml"
    T = np.eye(4)
    T[:3, :3] = [[0, 1, 0], [0, 0, 1], [1, 0, 0]]  # cam <- IMU: IMU x is the camera's z, ...
    chain.write_text(yaml.safe_dump({"cam0": dict(
        camera_model="pinhole", distortion_model="none", distortion_coeffs=[],
        intrinsics=[30.0, 30.0, 31.5, 23.5], resolution=[64, 48], rostopic="/cam0/image_raw",
        T_cam_imu=T.tolist())}))
    tilt = np.array([0.2, 0.0, -0.98])  # IMU frame: mostly -z, i.e. the camera's -y: up
    msgs = [("/cam0/image_raw", image_msg(ROS2, frame(i), 3, i * 10**8), 2 * i) for i in range(2)]
    msgs += [("/imu0", imu_msg(ROS2, 9.81 * tilt, 3, k * 10**7), 2 * (k // 10) + 1) for k in range(20)]
    bag = write_bag(tmp_path / "run", False, msgs)
    cv2.imwrite(str(tmp_path / "f0.png"), cv2.cvtColor(frame(0), cv2.COLOR_RGB2BGR))
    tiny_seg_checkpoint(tmp_path / "seg.pt")
    ckpt = str(tmp_path / "seg.pt")
    assert main(["predict", "seg", ckpt, str(bag), "--camera", str(chain), "--imu", "/imu0",
                 "--out", str(tmp_path / "b")]) == 0
    up = cameras.imu_rotation(chain) @ tilt / np.linalg.norm(tilt)
    assert up[2] > 0.97  # the camera is nearly level
    out = capsys.readouterr().out
    assert given_up(up) in out
    assert main(["predict", "seg", ckpt, str(tmp_path / "f0.png"), "--camera", str(chain),
                 "--up", *map(str, up), "--out", str(tmp_path / "p")]) == 0
    a = cv2.imread(str(tmp_path / "b" / "run_000000_labels.png"), cv2.IMREAD_UNCHANGED)
    b = cv2.imread(str(tmp_path / "p" / "f0_labels.png"), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(a, b)
    capsys.readouterr()
    assert main(["predict", "seg", ckpt, str(tmp_path / "f0.png"), "--camera", str(chain),
                 "--imu", "/imu0"]) == 2
    assert "--imu reads up from a ROS bag's accelerometer" in capsys.readouterr().err
    assert main(["predict", "seg", ckpt, str(bag), "--imu", "/imu0"]) == 2
    assert "--imu needs the camera-IMU extrinsics" in capsys.readouterr().err


def test_render_levels_each_frame_by_the_imu(tmp_path, capsys):
    """``render BAG --imu``: each frame re-imaged with the camera turned level by the up the
    IMU reads at its stamp (two stamps, two tilts: the geometry built twice), as a
    Reimager of the turned camera gives it."""
    from scipy import ndimage

    from tests.frontend.test_rig import shoot
    from tests.helpers import decode_video
    from usf_graph.cli import main
    from usf_graph.frontend import Reimager
    from usf_graph.geometry import level_rotation

    chain = tmp_path / "camchain-imucam.yaml"
    T = np.eye(4)
    T[:3, :3] = [[0, 1, 0], [0, 0, 1], [1, 0, 0]]  # cam <- IMU, as above
    chain.write_text(yaml.safe_dump({"cam0": dict(
        camera_model="pinhole", distortion_model="none", distortion_coeffs=[],
        intrinsics=[30.0, 30.0, 31.5, 23.5], resolution=[64, 48], rostopic="/cam0/image_raw",
        T_cam_imu=T.tolist())}))
    cam = cameras.load(chain)
    shots = [(255 * shoot(cam.turned(level_rotation(np.array([0.1 * k, 0.0, 1.0]))))).round().astype(np.uint8)
             for k in range(2)]
    tilts = [np.array([0.2, 0.0, -0.98]), np.array([0.0, 0.3, -0.95])]  # the IMU's frame
    msgs = [("/cam0/image_raw", image_msg(ROS2, shots[i], 3 + i, 0), 2 * i) for i in range(2)]
    msgs += [("/imu0", imu_msg(ROS2, 9.81 * tilts[k // 10], 3 + k // 10, (k % 10) * 10**7), 2 * (k // 10) + 1)
             for k in range(20)]
    bag = write_bag(tmp_path / "run", False, msgs)
    pano = cameras.Equirectangular(128, 64)
    assert main(["render", str(bag), "--camera", str(chain), "--imu", "/imu0", "--to",
                 "equirectangular:128x64", "--out", str(tmp_path / "v.avi")]) == 0
    assert "geometry built 2 times for 2 frames" in capsys.readouterr().out
    got, _ = decode_video(tmp_path / "v.avi")
    ups = [cameras.imu_rotation(chain) @ t / np.linalg.norm(t) for t in tilts]
    for k, (g, shot) in enumerate(zip(got, shots)):
        err = []
        for up in (ups[k], ups[1 - k]):  # its own up, and the other frame's
            r = Reimager(cam.turned(level_rotation(up)), pano)
            inner = ndimage.binary_erosion(r.seen, iterations=2)  # JPEG rings at the view's edge
            err.append(np.abs(g.astype(float) - r(shot))[inner].mean())
        assert err[0] < 5 and err[1] > 3 * err[0], err  # Motion JPEG; the other up is far off
    for flags, why in ((["--level"], "not with --level"), (["--imu-up", "orientation"], "give --imu")):
        imu = [] if "--imu-up" in flags else ["--imu", "/imu0"]
        assert main(["render", str(bag), "--camera", str(chain), *imu, *flags, "--to",
                     "equirectangular:64x32", "--out", str(tmp_path / "x.avi")]) == 2
        assert why in capsys.readouterr().err


def test_imu_time_shift_of_every_format(tmp_path):
    """Kalibr's ``timeshift_cam_imu`` (seconds, per camera) and Basalt's
    ``cam_time_offset_ns``, both t_imu = t_cam + shift, in ns; 0 where there is none."""
    chain = yaml.safe_load((FIXTURES / "kalibr_camchain.yaml").read_text())
    chain["cam0"]["timeshift_cam_imu"] = 0.0123
    chain["cam1"]["timeshift_cam_imu"] = -0.0021
    kalibr = tmp_path / "camchain-imucam.yaml"
    kalibr.write_text(yaml.safe_dump(chain))
    assert cameras.imu_time_shift(kalibr) == 12_300_000
    assert cameras.imu_time_shift(kalibr, "cam1") == -2_100_000
    assert cameras.imu_time_shift(FIXTURES / "kalibr_rig.yaml") == 0  # none given
    calib = json.loads((FIXTURES / "basalt_calib.json").read_text())
    calib["value0"]["cam_time_offset_ns"] = -4567
    basalt = tmp_path / "calibration.json"
    basalt.write_text(json.dumps(calib))
    assert cameras.imu_time_shift(basalt, "cam1") == -4567
    assert cameras.imu_time_shift(FIXTURES / "orbslam3_stereo_kb8.yaml") == 0
    with pytest.raises(ValueError, match="no camera 'cam9'"):
        cameras.imu_time_shift(kalibr, "cam9")
    with pytest.raises(ValueError, match="no camera-IMU time shift"):
        cameras.imu_time_shift(FIXTURES / "ros_plumb_bob.yaml")
    chain["cam0"]["timeshift_cam_imu"] = float("nan")
    kalibr.write_text(yaml.safe_dump(chain))
    with pytest.raises(ValueError, match="'timeshift_cam_imu' must be finite"):
        cameras.imu_time_shift(kalibr)


def test_predict_reads_the_imu_at_the_shifted_stamp(tmp_path, capsys):
    """The IMU tilts at 0.15 s; a frame stamped 0.1 s by a camera whose clock runs 0.1 s
    behind the IMU's (``timeshift_cam_imu: 0.1``) must read the tilted up."""
    from usf_graph.cli import main

    T = np.eye(4)
    T[:3, :3] = [[0, 1, 0], [0, 0, 1], [1, 0, 0]]
    cam0 = dict(camera_model="pinhole", distortion_model="none", distortion_coeffs=[],
                intrinsics=[30.0, 30.0, 31.5, 23.5], resolution=[64, 48],
                rostopic="/cam0/image_raw", T_cam_imu=T.tolist())
    level, tilted = np.array([0.0, 0.0, -1.0]), np.array([0.3, 0.0, -0.95])
    msgs = [("/cam0/image_raw", image_msg(ROS2, frame(0), 0, 10**8), 10**8)]
    msgs += [("/imu0", imu_msg(ROS2, 9.81 * (level if k < 15 else tilted), 0, k * 10**7),
              k * 10**7) for k in range(30)]
    bag = write_bag(tmp_path / "run", False, msgs)
    tiny_seg_checkpoint(tmp_path / "seg.pt")
    for shift, acc in ((0.0, level), (0.1, tilted)):
        chain = tmp_path / f"chain_{shift}.yaml"
        chain.write_text(yaml.safe_dump({"cam0": {**cam0, "timeshift_cam_imu": shift}}))
        assert main(["predict", "seg", str(tmp_path / "seg.pt"), str(bag), "--camera",
                     str(chain), "--imu", "/imu0", "--imu-window", "30",
                     "--out", str(tmp_path / f"out_{shift}")]) == 0
        up = cameras.imu_rotation(chain) @ (acc / np.linalg.norm(acc))
        assert given_up(up) in capsys.readouterr().out
    # the window, in ms about the stamp: 100 by default (readings 5-15, one tilted), or 120 (4-16)
    chain = tmp_path / "chain_0.0.yaml"  # no shift
    for window, (lo, hi) in ((None, (5, 15)), ("120", (4, 16))):
        assert main(["predict", "seg", str(tmp_path / "seg.pt"), str(bag), "--camera", str(chain),
                     "--imu", "/imu0", *(["--imu-window", window] if window else []),
                     "--out", str(tmp_path / "w")]) == 0
        acc = np.mean([level if k < 15 else tilted for k in range(lo, hi + 1)], 0)
        up = cameras.imu_rotation(chain) @ (acc / np.linalg.norm(acc))
        assert given_up(up) in capsys.readouterr().out


def ramp(h=48, w=64):
    """Linear ramps, a different one per channel: demosaicking reproduces them exactly away
    from the border, and any swap of channels or Bayer phase shows."""
    y, x = np.mgrid[:h, :w]
    return np.stack([40 + 3 * x, 30 + 4 * y, 200 - 2 * x - y], -1).astype(np.float64)


def raw_image(encoding: str, rgb: np.ndarray) -> np.ndarray:
    """``rgb`` as a raw sensor_msgs/Image's pixels in ``encoding`` (ROS's Bayer phases:
    ``rggb`` has red at row 0, column 0)."""
    deep = encoding.endswith("16")
    if encoding.startswith("bayer_"):
        pattern = encoding[6:10]
        out = np.zeros(rgb.shape[:2])
        for (dy, dx), c in zip(((0, 0), (0, 1), (1, 0), (1, 1)), pattern):
            out[dy::2, dx::2] = rgb[dy::2, dx::2, "rgb".index(c)]
    else:
        base = encoding.removesuffix("16").removesuffix("8")
        out = {"rgb": rgb, "bgr": rgb[..., ::-1], "mono": rgb[..., 0]}[base.removesuffix("a")]
        if base.endswith("a"):
            out = np.concatenate([out, np.full(out.shape[:2] + (1,), 255.0)], -1)
    return (out * 257).astype(np.uint16) if deep else out.astype(np.uint8)


@pytest.mark.parametrize("encoding", ["bayer_rggb8", "bayer_bggr8", "bayer_gbrg8",
                                      "bayer_grbg8", "bayer_rggb16", "rgb16", "bgr16",
                                      "rgba8", "bgra8", "mono16", "mono16_big_endian"])
def test_bayer_16_bit_and_alpha_encodings_read_as_the_scene(tmp_path, encoding):
    T = ROS2.types
    big = encoding.endswith("_big_endian")
    enc = encoding.removesuffix("_big_endian")
    pixels = raw_image(enc, ramp())
    if big:
        pixels = pixels.astype(">u2")
    header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=0),
                                      frame_id="cam")
    msg = T["sensor_msgs/msg/Image"](header=header, height=48, width=64, encoding=enc,
                                     is_bigendian=int(big), step=pixels[0].nbytes,
                                     data=np.ascontiguousarray(pixels).view(np.uint8).reshape(-1))
    img = next(bags.frames(write_bag(tmp_path / "b", False, [("/cam/image_raw", msg, 1)]))).image
    want = ramp()[..., 0] if enc.startswith("mono") else ramp()
    assert img.shape == want.shape  # colour as RGB (no alpha), mono as mono
    assert img.dtype == (np.uint16 if enc == "mono16" else np.uint8)  # colour to 8 bits
    got = img.astype(np.float64) / (257 if img.dtype == np.uint16 else 1)
    np.testing.assert_array_equal(got[2:-2, 2:-2], want[2:-2, 2:-2])


def test_the_imu_orientation_gives_up_while_the_platform_accelerates(tmp_path):
    """An attitude filter's orientation (world <- IMU, REP-145) gives the world's up in the
    IMU's frame, R^T e_z (scipy's rotation the reference), while the accelerometer, which
    also reads the platform's acceleration, is tilted away from it."""
    from scipy.spatial.transform import Rotation

    Q = Rotation.from_rotvec([0.3, -0.5, 1.2])  # world <- IMU
    up = Q.inv().apply([0.0, 0.0, 1.0])
    accel = Q.inv().apply([3.0, 0.0, 9.81])  # braking/accelerating at 3 m/s^2
    msgs = [("/imu", imu_msg(ROS2, accel, 7, i * 10**7, quat=Q.as_quat()), i) for i in range(20)]
    bag = write_bag(tmp_path / "imu", False, msgs)
    u = bags.ImuOrientation(bag, "/imu").up(7 * 10**9 + 10**8)
    np.testing.assert_allclose(u, up, atol=1e-12)
    a = bags.Accelerometer(bag, "/imu").up(7 * 10**9 + 10**8)
    assert np.degrees(np.arccos(a @ up)) > 15  # the accelerometer tilts by atan(3 / 9.81)
    unknown = [("/imu", imu_msg(ROS2, accel, 7, 0, no_orientation=True), 0)]
    with pytest.raises(ValueError, match=r"gives no orientation .*--imu-up accel"):
        bags.ImuOrientation(write_bag(tmp_path / "none", False, unknown), "/imu")
    zero = [("/imu", imu_msg(ROS2, accel, 7, 0, quat=(0, 0, 0, 0)), 0)]
    with pytest.raises(ValueError, match="is not a rotation"):
        bags.ImuOrientation(write_bag(tmp_path / "zero", False, zero), "/imu")


def test_predict_reads_up_from_the_imu_orientation(tmp_path, capsys):
    from scipy.spatial.transform import Rotation

    from usf_graph.cli import main

    T = np.eye(4)
    T[:3, :3] = [[0, 1, 0], [0, 0, 1], [1, 0, 0]]
    chain = tmp_path / "camchain-imucam.yaml"
    chain.write_text(yaml.safe_dump({"cam0": dict(
        camera_model="pinhole", distortion_model="none", distortion_coeffs=[],
        intrinsics=[30.0, 30.0, 31.5, 23.5], resolution=[64, 48], rostopic="/cam0/image_raw",
        T_cam_imu=T.tolist())}))
    Q = Rotation.from_rotvec([0.1, 1.4, 0.2])  # world <- IMU: IMU x nearly up
    msgs = [("/cam0/image_raw", image_msg(ROS2, frame(0), 3, 0), 0)]
    msgs += [("/imu0", imu_msg(ROS2, (0.0, 5.0, 0.0), 3, 0, quat=Q.as_quat()), 1)]
    bag = write_bag(tmp_path / "run", False, msgs)
    tiny_seg_checkpoint(tmp_path / "seg.pt")
    ckpt = str(tmp_path / "seg.pt")
    assert main(["predict", "seg", ckpt, str(bag), "--camera", str(chain), "--imu", "/imu0",
                 "--imu-up", "orientation", "--out", str(tmp_path / "o")]) == 0
    up = cameras.imu_rotation(chain) @ Q.inv().apply([0.0, 0.0, 1.0])
    assert given_up(up) in capsys.readouterr().out
    assert main(["predict", "seg", ckpt, str(bag), "--camera", str(chain),
                 "--imu-up", "orientation"]) == 2
    assert "--imu-up says how to read --imu's messages" in capsys.readouterr().err


@pytest.mark.parametrize("command", [["predict", "seg", "m.pt", "x.bag"], ["render", "x.bag", "--to", "equirectangular:64x32", "--out", "x.mp4"]])
def test_the_bag_options_default_to_the_readers_own(command):
    """``--max-skew`` and ``--imu-window`` (ms) default to what ``rig_frames`` and the IMU
    readers take (ns) when called from Python."""
    from usf_graph.cli import build_parser
    from usf_graph.train.engine import defaults

    args = build_parser().parse_args(command)
    assert round(args.max_skew * 1e6) == defaults(bags.rig_frames)["max_skew_ns"]
    assert round(args.imu_window * 1e6) == defaults(bags.Accelerometer.up)["window_ns"]
    assert args.imu_up == "accel"
