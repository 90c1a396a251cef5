"""The commands' ROS bag parts: ``usf-graph bag``, a bag's camera and IMU for ``predict``,
and ``predict --rig`` on a rig's recording."""

from __future__ import annotations

from pathlib import Path

from .cli_inputs import alpha_masked, rig_from_spec


def cmd_bag(args) -> int:
    """``usf-graph bag PATH``: the topics ``predict`` can read, and where the camera_info is."""
    from .bags import summary

    s = summary(args.bag)
    print(f"{'image topic':<40} {'type':<16} {'messages':>8}  camera_info")
    for t, (kind, n, info) in s["images"].items():
        print(f"{t:<40} {kind:<16} {n:>8}  {info or '- (give --camera)'}")
    if not s["images"]:
        print("(no sensor_msgs/Image or CompressedImage topic)")
    for t, n in s["imu"].items():
        print(f"IMU {t} ({n} messages): predict --imu {t}")
    if s["other"]:
        print("other topics: " + ", ".join(f"{t} ({m.rsplit('/', 1)[1]})" for t, (m, _) in s["other"].items()))
    return 0


def bag_options(p, imu_gives: str) -> None:
    """``--max-skew``, and ``--imu`` (giving ``imu_gives``), ``--imu-window``, ``--imu-up``:
    a ROS bag's rig frames and IMU."""
    p.add_argument("--max-skew", type=float, default=10.0, metavar="MS",
                   help="a rig's ROS bag: the most the cameras' stamps of one frame may differ")
    p.add_argument("--imu", default=None, metavar="TOPIC",
                   help="ROS bags: this sensor_msgs/Imu topic's accelerometer, turned by "
                        "--camera's camera-IMU extrinsics (Kalibr T_cam_imu, Basalt T_imu_cam, "
                        f"ORB-SLAM3 IMU.T_b_c1), gives {imu_gives}")
    p.add_argument("--imu-window", type=float, default=100.0, metavar="MS",
                   help="--imu: the readings averaged about each frame's stamp")
    p.add_argument("--imu-up", choices=("accel", "orientation"), default="accel",
                   help="--imu: up from the accelerometer (tilted while the platform "
                        "accelerates), or from the orientation the IMU's attitude filter "
                        "fills in (a gravity-aligned world frame, REP-145)")


def bag_camera(bag, topic, args):
    """The camera of ``topic``'s images from the bag's camera_info, with ``--fov`` and
    ``--image-mask``."""
    from .bags import camera
    from .cameras import with_fov_and_mask

    cam = with_fov_and_mask(camera(bag, topic), args.fov, args.image_mask)
    print(f"camera from {bag}'s camera_info: {cam}")
    return cam


def imu_up(args, rig: bool | None = None):
    """``--imu``: (bag, stamp) -> up in the cameras' sphere frame, or None. ``rig``: whether
    the frames are a rig's (default ``args.rig``), stamped by its first camera."""
    if args.imu is None:
        return None
    from .bags import IMU_SOURCES
    from .cameras import imu_rotation, imu_time_shift

    if args.camera is None:
        raise ValueError("--imu needs the camera-IMU extrinsics: give --camera (a Kalibr "
                         "camchain-imucam, Basalt calibration or ORB-SLAM3 settings)")
    R = imu_rotation(args.camera)
    # a rig's frames are stamped by its first camera; one camera's by --key's
    shift = imu_time_shift(args.camera, None if (args.rig if rig is None else rig) else args.key)
    readings = {}

    def up(bag, stamp):
        if bag not in readings:
            readings[bag] = IMU_SOURCES[args.imu_up](bag, args.imu)
        return R @ readings[bag].up(stamp + shift, round(args.imu_window * 1e6))
    return up


def predict_rig_bag(run, model, names, out: Path, args) -> None:
    """``predict --rig`` on a ROS bag: each camera's topic, frames matched by stamp."""
    from .bags import rig_frames
    from .cameras import rig_topics

    bag = args.image[0]
    auto = args.distance == "auto"
    rig = rig_from_spec(args.camera, args.fov, args.image_mask, args.key,
                        None if auto else args.distance)
    topics = args.topic or rig_topics(args.camera)
    if topics is None:
        raise ValueError(f"--rig on a bag: give each camera's image topic with --topic, in the "
                         f"rig's order ({', '.join(rig)}); {args.camera} names none")
    if len(topics) != len(rig):
        raise ValueError(f"--rig: {args.camera} has {len(rig)} cameras ({', '.join(rig)}) but "
                         f"{len(topics)} topics were given ({', '.join(topics)})")
    print(f"rig {', '.join(f'{n} <- {t}' for n, t in zip(rig, topics))}")
    name = Path(bag).stem
    imu, fitted = imu_up(args), False
    for f in rig_frames(bag, topics, args.every, round(args.max_skew * 1e6)):
        sources = [f"{bag}#{t}@{s}" for t, s in zip(topics, f.stamps_ns)]
        print(f"== {bag}#{f.index} ({', '.join(str(s) for s in f.stamps_ns)})")
        if not fitted:  # to the first frame's sizes ('auto': its distance), kept for the rest
            rig = rig_from_spec(args.camera, args.fov, args.image_mask, args.key, args.distance,
                                f.images)
            fitted = True
        cams = {n: alpha_masked(c, im, s) for (n, c), im, s in zip(rig.items(), f.images, sources)}
        run(model, [f"{name}_{n}_{f.index:06d}" for n in rig], sources, f.images, cams, names,
            out, args, up=None if imu is None else imu(bag, f.stamps_ns[0]))
