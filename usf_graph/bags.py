"""ROS bags: a camera's images and its calibration, read from a recording.

ROS 1 (``.bag``) and ROS 2 (a folder with ``metadata.yaml``, or its ``.db3`` / ``.mcap``)
through the ``rosbags`` library (``pip install usf-graph[ros]``). Images are
``sensor_msgs/Image`` (any encoding ``rosbags-image`` converts: colour as RGB, mono as one
channel) or ``sensor_msgs/CompressedImage``; the calibration is the first
``sensor_msgs/CameraInfo`` next to the image topic (``/ns/image_raw`` ->
``/ns/camera_info``), read as ROS writes it: plumb_bob, rational_polynomial or equidistant.
Frames are read one at a time, so a long recording never sits in memory.

    from usf_graph import bags
    cam = bags.camera("run.bag", "/cam0/image_raw")
    for f in bags.frames("run.bag", "/cam0/image_raw", every=10):
        f.index, f.stamp_ns, f.image  # [H, W, 3] RGB or [H, W]
"""

from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .cameras import Camera
from .cameras.formats import camera_info_to_camera
from .geometry import rotation_from_quaternion

#: Files read as ROS bags (besides a ROS 2 bag's folder).
BAG_SUFFIXES = (".bag", ".db3", ".mcap")
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
INFO_TYPE = "sensor_msgs/msg/CameraInfo"
_MONO = ("mono8", "mono16", "8uc1", "16uc1")


class Frame(NamedTuple):
    """One image message of a bag, decoded (what :func:`frames` and :func:`rig_frames` yield)."""

    topic: str
    index: int  # the message's place on its topic, from 0
    stamp_ns: int  # the header's stamp (the recording time where the stamp is 0)
    image: np.ndarray  # [H, W, 3] RGB or [H, W] mono


def is_bag(path) -> bool:
    """True for a ROS 1 ``.bag``, a ROS 2 ``.db3``/``.mcap`` or a ROS 2 bag's folder."""
    p = Path(path)
    return p.suffix.lower() in BAG_SUFFIXES or (p.is_dir() and (p / "metadata.yaml").is_file())


def _open(path):
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise ImportError("reading ROS bags needs rosbags: pip install 'usf-graph[ros]' "
                          "(rosbags and rosbags-image)") from None
    p = Path(path)
    if p.suffix.lower() in (".db3", ".mcap") and (p.parent / "metadata.yaml").is_file():
        p = p.parent  # rosbags opens a ROS 2 bag by its folder
    if not p.exists():
        raise FileNotFoundError(f"ROS bag {path} does not exist")
    try:
        reader = AnyReader([p], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as e:  # noqa: BLE001 - rosbags raises its own errors for bad files
        raise ValueError(f"cannot read ROS bag {path} ({type(e).__name__}: {e}); a ROS 2 bag "
                         "is opened by its folder (with metadata.yaml)") from e
    return reader


def topics(path) -> dict[str, tuple[str, int]]:
    """``{topic: (message type, count)}`` of every topic in the bag."""
    reader = _open(path)
    try:
        return {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}
    finally:
        reader.close()


def _messages(path, wanted) -> Iterator[tuple]:
    """``(topic, recording time, load)`` of every message on the ``wanted`` topics, in
    recording order; ``load()`` deserializes it (so messages nobody needs are not)."""
    reader = _open(path)
    try:
        conns = [c for c in reader.connections if c.topic in wanted]
        for conn, t, raw in reader.messages(connections=conns):
            yield conn.topic, t, lambda conn=conn, raw=raw: reader.deserialize(raw, conn.msgtype)
    finally:
        reader.close()


def _of(found: dict, types) -> list[str]:
    """The topics of ``found`` (:func:`topics`) whose message type is one of ``types``."""
    return [t for t, (m, _) in found.items() if m in types]


def image_topic(path, topic: str | None = None, found: dict | None = None) -> str:
    """``topic`` checked to be an image topic of the bag, or the bag's only image topic;
    ``found``: the bag's :func:`topics`, where the caller has them."""
    images = _of(topics(path) if found is None else found, IMAGE_TYPES)
    if topic is None:
        if len(images) != 1:
            raise ValueError(f"{path} has {len(images)} image topics ({', '.join(sorted(images)) or 'none'}); "
                             "choose one with --topic" if images else
                             f"{path} has no sensor_msgs/Image or CompressedImage topic")
        return images[0]
    if topic not in images:
        raise ValueError(f"{path}: no image topic {topic!r}; its image topics: "
                         f"{', '.join(sorted(images)) or 'none'}")
    return topic


def frames(path, topic: str | None = None, every: int = 1) -> Iterator[Frame]:
    """Every ``every``-th image of ``topic`` (the bag's only image topic when None), in
    recording order."""
    topic = image_topic(path, topic)
    for i, (_, t, load) in enumerate(_messages(path, {topic})):
        if i % every == 0:
            msg = load()
            yield Frame(topic, i, _stamp(msg, t), _image(msg, f"{path} [{topic} #{i}]"))


class RigFrame(NamedTuple):
    index: int  # the first topic's message index
    stamps_ns: tuple  # each camera's stamp
    images: list  # one image per topic, in the topics' order


def rig_frames(path, rig_topics, every: int = 1, max_skew_ns: int = 10**7) -> Iterator[RigFrame]:
    """A rig's frames: for every ``every``-th image of the first topic, the image of every
    other topic whose stamp is nearest to it, when all are within ``max_skew_ns``; sets
    where a camera has none that near are skipped (and counted in a warning)."""
    found = topics(path)
    rig_topics = [image_topic(path, t, found) for t in rig_topics]
    if len(set(rig_topics)) < len(rig_topics):
        raise ValueError(f"a rig's cameras need one topic each, got {rig_topics}")
    stamps = _stamps(path, rig_topics)
    want, skipped = {}, 0  # (topic index, message index) -> set index
    sets = []
    for i in range(0, len(stamps[0]), every):
        t0, pick = stamps[0][i], [i]
        for st in stamps[1:]:
            j = int(np.argmin(np.abs(st - t0))) if len(st) else -1
            pick.append(j if j >= 0 and abs(int(st[j]) - int(t0)) <= max_skew_ns else None)
        if None in pick:
            skipped += 1
            continue
        sets.append(pick)
        for k, j in enumerate(pick):
            want.setdefault((k, j), []).append(len(sets) - 1)
    if not sets:
        raise ValueError(f"{path}: no frame of {rig_topics[0]} has an image of every other "
                         f"camera ({', '.join(rig_topics[1:])}) within {max_skew_ns / 1e6:g} ms; "
                         "raise the tolerance (--max-skew) or check the topics")
    if skipped:
        import warnings

        warnings.warn(f"{path}: {skipped} of the {skipped + len(sets)} frames of {rig_topics[0]} "
                      f"have no image of every other camera within {max_skew_ns / 1e6:g} ms; "
                      "they are left out", stacklevel=2)
    got: dict = {}  # set index -> {camera: image}; sets are given out as they complete
    seen = dict.fromkeys(rig_topics, -1)
    for topic, _, load in _messages(path, set(rig_topics)):
        k = rig_topics.index(topic)
        seen[topic] += 1
        users = want.get((k, seen[topic]))
        if not users:
            continue
        img = _image(load(), f"{path} [{topic} #{seen[topic]}]")
        for u in users:
            got.setdefault(u, {})[k] = img
            if len(got[u]) == len(rig_topics):
                done = got.pop(u)
                pick = sets[u]
                yield RigFrame(pick[0], tuple(int(stamps[c][j]) for c, j in enumerate(pick)),
                               [done[c] for c in range(len(rig_topics))])


def _stamps(path, topics_: list) -> list[np.ndarray]:
    """Each topic's message stamps (ns), in its order (the header's; the recording time
    where the stamp is 0)."""
    out = {t: [] for t in topics_}
    for topic, t, load in _messages(path, out):
        out[topic].append(_stamp(load(), t))
    return [np.array(out[t], np.int64) for t in topics_]


IMU_TYPE = "sensor_msgs/msg/Imu"


class Accelerometer:
    """A bag's ``sensor_msgs/Imu`` readings, for the direction of up at any stamp.

    At rest an accelerometer reads the specific force, ``+g`` away from the earth: the mean
    of its readings about a frame's stamp is up in the IMU's frame, to the platform's own
    acceleration over that window (a robot that brakes hard tilts it; read the IMU's own
    attitude estimate with :class:`ImuOrientation` instead, where it gives one)."""

    def __init__(self, path, topic: str):
        found = _of(topics(path), (IMU_TYPE,))
        if topic not in found:
            raise ValueError(f"{path}: no sensor_msgs/Imu topic {topic!r}; its IMU topics: "
                             f"{', '.join(sorted(found)) or 'none'}")
        self.path, self.topic = path, topic
        stamps, readings = [], []
        for i, (_, t, load) in enumerate(_messages(path, {topic})):
            msg = load()
            stamps.append(_stamp(msg, t))
            readings.append(self._reading(msg, f"{path} [{topic} #{i}]"))
        order = np.argsort(stamps, kind="stable")
        self.stamps = np.asarray(stamps, np.int64)[order]
        #: Each stamp's up-pointing reading ``[T, 3]`` in the IMU's frame (not unit for the
        #: accelerometer); ``stamps [T]`` in ns, sorted.
        self.readings = np.asarray(readings, np.float64).reshape(-1, 3)[order]

    @staticmethod
    def _reading(msg, where: str) -> tuple:
        a = msg.linear_acceleration
        return a.x, a.y, a.z

    def up(self, stamp_ns: int, window_ns: int = 10**8) -> np.ndarray:
        """Unit up ``[3]`` in the IMU's frame: the mean reading within ``window_ns / 2`` of
        ``stamp_ns`` (the nearest reading where none is that near, if within the window)."""
        lo = int(np.searchsorted(self.stamps, stamp_ns - window_ns // 2, side="left"))
        hi = int(np.searchsorted(self.stamps, stamp_ns + window_ns // 2, side="right"))
        if hi > lo:
            a = self.readings[lo:hi].mean(0)
        else:
            j = int(np.argmin(np.abs(self.stamps - stamp_ns))) if len(self.stamps) else -1
            if j < 0 or abs(int(self.stamps[j]) - stamp_ns) > window_ns:
                raise ValueError(f"{self.path} [{self.topic}]: no IMU reading within "
                                 f"{window_ns / 1e6:g} ms of the frame at {stamp_ns} ns")
            a = self.readings[j]
        n = float(np.linalg.norm(a))
        if not np.isfinite(n) or n < 0.1:  # a free fall, or no data (0.1: g units pass too)
            raise ValueError(f"{self.path} [{self.topic}]: the accelerometer reads {n:.3g} m/s^2 "
                             f"about {stamp_ns} ns, too little to tell up")
        return a / n


class ImuOrientation(Accelerometer):
    """Up from the ``orientation`` an IMU's attitude filter fills in (REP-145: the IMU's
    frame in a world frame whose z points up, as most drivers and ``robot_localization``
    give it): ``R^T e_z``, the world's up in the IMU's frame, averaged about each stamp as
    :class:`Accelerometer` averages its readings. Unlike the raw accelerometer it does not
    tilt while the platform accelerates. Messages whose ``orientation_covariance[0]`` is
    -1 (the message's "no orientation") are refused."""

    @staticmethod
    def _reading(msg, where: str) -> tuple:
        if msg.orientation_covariance[0] == -1:
            raise ValueError(f"{where}: the IMU gives no orientation (orientation_covariance[0] "
                             "is -1); read up from its accelerometer instead (--imu-up accel)")
        q = np.array([msg.orientation.w, msg.orientation.x, msg.orientation.y,
                      msg.orientation.z], np.float64)
        if not np.isfinite(q).all() or np.linalg.norm(q) < 0.5:  # drivers write unit ones
            raise ValueError(f"{where}: the IMU's orientation {q.tolist()} (w, x, y, z) is "
                             "not a rotation")
        R = rotation_from_quaternion(q)  # world <- IMU
        return tuple(R[2])  # R^T e_z


#: How an IMU topic gives up: the accelerometer, or the attitude filter's orientation.
IMU_SOURCES = {"accel": Accelerometer, "orientation": ImuOrientation}


def _stamp(msg, t: int) -> int:
    """The header's stamp in ns; the recording time ``t`` where the stamp is 0."""
    s = msg.header.stamp
    return s.sec * 10**9 + s.nanosec or t


def _image(msg, where: str) -> np.ndarray:
    import cv2

    if hasattr(msg, "format"):  # CompressedImage: PNG or JPEG bytes
        img = cv2.imdecode(np.asarray(msg.data, np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError(f"{where}: the compressed image ({msg.format!r}) does not decode")
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB if img.shape[2] == 3 else cv2.COLOR_BGRA2RGBA)
        return img
    from rosbags.image import message_to_cvimage

    try:
        if msg.encoding.lower() in _MONO:
            return message_to_cvimage(msg)
        return message_to_cvimage(msg, "rgb8")
    except Exception as e:  # noqa: BLE001 - an encoding rosbags-image does not convert
        raise ValueError(f"{where}: cannot convert the image (encoding {msg.encoding!r}: "
                         f"{e})") from e


def _beside(topic: str) -> str:
    base = topic.rsplit("/compressed", 1)[0] if topic.endswith("/compressed") else topic
    return base.rsplit("/", 1)[0] + "/camera_info"


def _info_topic(topic: str, infos: list, images: list) -> str | None:
    """The camera_info topic of an image topic: the one beside it, else the bag's only one
    when all its image topics are one camera's (raw and compressed)."""
    if _beside(topic) in infos:
        return _beside(topic)
    one_camera = len({_beside(t) for t in images}) == 1
    return infos[0] if len(infos) == 1 and one_camera else None


def summary(path) -> dict:
    """What a bag holds for usf-graph: ``images`` (``{topic: (type, count, camera_info
    topic or None)}``), ``imu`` (``{topic: count}``) and ``other`` (``{topic: (type,
    count)}``)."""
    found = topics(path)
    infos, images = _of(found, (INFO_TYPE,)), _of(found, IMAGE_TYPES)
    out = {"images": {}, "imu": {}, "other": {}}
    for t, (m, n) in sorted(found.items()):
        if m in IMAGE_TYPES:
            out["images"][t] = (m.rsplit("/", 1)[1], n, _info_topic(t, infos, images))
        elif m == IMU_TYPE:
            out["imu"][t] = n
        else:
            out["other"][t] = (m, n)
    return out


def camera(path, topic: str | None = None) -> Camera:
    """The camera of ``topic``'s images from the bag's ``sensor_msgs/CameraInfo``: the one
    beside it (``/ns/image_raw[/compressed]`` -> ``/ns/camera_info``), else the bag's only
    one when the bag holds one camera's images. Its first message is used."""
    found = topics(path)
    topic = image_topic(path, topic, found)
    infos = _of(found, (INFO_TYPE,))
    name = _info_topic(topic, infos, _of(found, IMAGE_TYPES))
    if name is None:
        raise ValueError(f"{path}: no camera_info for {topic} (looked for {_beside(topic)}; the "
                         f"bag's: {', '.join(infos) or 'none'}); give the calibration with --camera")
    messages = _messages(path, {name})
    try:
        msg = next(messages)[2]()  # the first message
    finally:
        messages.close()
    if getattr(msg, "binning_x", 0) > 1 or getattr(msg, "binning_y", 0) > 1 or msg.roi.width:
        raise ValueError(f"{path} [{name}]: binned or cropped camera_info (binning "
                         f"{msg.binning_x}x{msg.binning_y}, roi {msg.roi.width}x{msg.roi.height}) "
                         "is not read; give the calibration of the images with --camera")
    return camera_info_to_camera(
        {"image_width": msg.width, "image_height": msg.height,
         "camera_matrix": {"data": np.asarray(msg.K if hasattr(msg, "K") else msg.k).tolist()},
         "distortion_model": msg.distortion_model,
         "distortion_coefficients": {"data": np.asarray(msg.D if hasattr(msg, "D") else msg.d).tolist()}},
        path, name)
