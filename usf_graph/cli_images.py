"""``usf-graph lift`` and ``usf-graph render``: an image (or a rig's images) through its
camera onto a grid, or into another camera's pixels."""

from __future__ import annotations

from itertools import chain
from pathlib import Path

from .cli_inputs import (
    camera_from_spec,
    check_panorama_videos,
    has_size,
    is_cubemap_spec,
    is_panorama_spec,
    leveled,
    read_image,
    rig_from_spec,
)
from .fileio import write_image
from .videos import frames as video_frames
from .videos import info as video_info
from .videos import is_video, split_frame


def read_images(args) -> list:
    """The images of ``args.image``; with ``args.split``, the one image cut into the rig's
    cameras' images, side by side (a dual-fisheye 360 camera's frame)."""
    images = [read_image(p) for p in args.image]
    if not getattr(args, "split", False):
        return images
    from .cameras import load_rig

    if len(images) != 1:
        raise ValueError("--split cuts one image into the rig's cameras' images; give one")
    return split_frame(images[0], len(load_rig(args.camera, key=args.key)), args.camera)


def _check_one_or_rig(args, rig: bool) -> None:
    """``--distance`` stitches a rig's cameras."""
    if not rig and args.distance is not None:
        raise ValueError("--distance stitches a rig's cameras; one image is seen from its own "
                         "camera's centre: give the rig's images to use it")


def cmd_lift(args) -> int:
    from . import grids
    from .frontend import RigFrontend, SphericalFrontend, save_lifted

    images = read_images(args)
    grid = grids.from_spec(args.grid)
    _check_one_or_rig(args, len(images) > 1)
    if len(images) > 1:
        rig = leveled(rig_from_spec(args.camera, args.fov, args.image_mask, args.key,
                                    args.distance, images, grid), images, args)
        fe = RigFrontend(rig, grid, interpolation=args.interpolation, blend=args.blend,
                         radius=args.radius)
        x = fe.lift(images)
    else:
        cam = camera_from_spec(args.camera, args.key, args.fov, args.image_mask, images[0].shape,
                               args.image[0])
        cam = leveled(cam, images[0], args)
        fe = SphericalFrontend(cam, grid, interpolation=args.interpolation, radius=args.radius)
        x = fe.lift(images[0])
    print(f"{fe}\n-> x {tuple(x.shape)}, {int(fe.mask.sum())}/{len(grid)} points visible")
    if args.preview:  # first: a suffix matplotlib cannot write stops before --out is written
        from .viz import plot_sphere

        v = x.float()  # RGB images in colour, other channel counts as their mean
        if v.shape[-1] == 4:
            v = v[:, :3]
        plot_sphere(grid.pos, v if v.shape[-1] == 3 else v.mean(-1), fe.mask, args.preview,
                    title=" + ".join(args.image))
        print(f"wrote {args.preview}")
    if args.out:
        save_lifted(args.out, x, fe, source=" ".join(args.image))
        size = Path(args.out).stat().st_size
        print(f"wrote {args.out} ({size / 1e6:.2f} MB: signal, mask and geometry spec; "
              "read it with usf_graph.frontend.load_lifted)")
    return 0


def _target(args, image):
    """``--to``: the camera asked for, not fitted to the source image; a panorama without a
    size gets the source's width, at 2:1."""
    if is_cubemap_spec(args.to) and not has_size(args.to):
        size = max(image.shape[1] // 4, 2)  # a face's 90 degrees, at the source's density
        eac = args.to.split(":")[0].lower() == "eac"
        return camera_from_spec(f"{args.to}:{3 * size}x{2 * size}" if eac else f"{args.to}:{size}",
                                args.to_key)
    return camera_from_spec(args.to, args.to_key, image_shape=(image.shape[1] // 2, image.shape[1])
                            if is_panorama_spec(args.to) else None)


def _sources(args, images, camera=None) -> tuple[dict, object]:
    """The source camera(s) fitted to the first frame (``images``: one, or one per camera of
    a rig; ``camera``: one camera's, where a ROS bag's camera_info gave it; leveled by
    ``--level``), ``{name: Camera}``, and the ``--to`` target."""
    if len(images) > 1 and (is_panorama_spec(args.to) or is_cubemap_spec(args.to)) and \
            not has_size(args.to):
        raise ValueError("a rig's images have no one width to take: give the panorama's size, "
                         "--to equirectangular:WIDTHxHEIGHT or cubemap:SIZE")
    dst = _target(args, images[0])
    _check_one_or_rig(args, len(images) > 1)
    if len(images) > 1:  # mounted level too: up from all the rig's lines
        return leveled(rig_from_spec(args.camera, args.fov, args.image_mask, args.key,
                                     args.distance, images), images, args), dst
    src = camera if camera is not None else \
        camera_from_spec(args.camera, args.key, args.fov, args.image_mask, images[0].shape,
                         args.image[0])
    return {"camera": leveled(src, images[0], args)}, dst  # mounted level: the target sees a level scene


def _reimager(args, cams: dict, dst, turn=None, fixed: dict | None = None):
    """What re-images one frame (a list of images, one per camera of ``cams``) into ``dst``,
    the cameras turned by ``turn`` (``[3, 3]``) where given, and what it says of itself.
    ``fixed``: what turning does not change, from an earlier call (``source_valid``, a list
    per camera, and ``target``)."""
    from .frontend import Reimager, RigReimager

    if turn is not None:
        cams = {n: c.turned(turn) for n, c in cams.items()}
    fixed = fixed or {}
    if len(cams) > 1:
        r = RigReimager(cams, dst, blend=args.blend, interpolation=args.interpolation, **fixed)
        return r, (f"rig of {len(cams)} ({', '.join(cams)}) -> {type(dst).__name__} "
                   f"{dst.width}x{dst.height}, blend {args.blend}")
    src = next(iter(cams.values()))
    valid = fixed.get("source_valid")
    one = Reimager(src, dst, interpolation=args.interpolation, target=fixed.get("target"),
                   source_valid=None if valid is None else valid[0])
    return (lambda ims: one(ims[0])), (f"{type(src).__name__} {src.width}x{src.height} -> "
                                       f"{type(dst).__name__} {dst.width}x{dst.height}")


class _LevelEachFrame:
    """``render --imu`` and ``--level-each``: each frame re-imaged with the cameras turned
    level by its own up (``up_of(images, stamp)``, in the source's sphere frame); the
    geometry rebuilt only when up moves by more than ``step`` degrees."""

    def __init__(self, args, cams, dst, up_of, step: float = 0.05):
        from .frontend.interpolation import valid_pixels

        self.args, self.cams, self.dst, self.up_of, self.step = args, cams, dst, up_of, step
        self.built, self.builds, self.reimage, self.tilts = None, 0, None, []
        # what a turn does not change, found once: each camera's readable pixels, the target's rays
        self.fixed = {"source_valid": [valid_pixels(c) for c in cams.values()],
                      "target": dst.lens_normal_map()}

    def __call__(self, images, stamp):
        import numpy as np

        from .geometry import geodesic_distance, level_rotation

        up = np.asarray(self.up_of(images, stamp), np.float64)
        up = up / np.linalg.norm(up)
        self.tilts.append(float(np.degrees(geodesic_distance(up, [0.0, 0.0, 1.0]))))
        if self.built is None or np.degrees(geodesic_distance(up, self.built)) > self.step:
            self.reimage, _ = _reimager(self.args, self.cams, self.dst, level_rotation(up), self.fixed)
            self.built, self.builds = up, self.builds + 1
        return self.reimage(images)


def _level_each(args, cams, dst):
    """The frame leveler of ``--imu`` or ``--level-each``, what it says of itself, and what
    it says at the end."""
    if args.imu is not None:
        from .cli_bags import imu_up

        up_at = imu_up(args, rig=len(cams) > 1)
        level = _LevelEachFrame(args, cams, dst, lambda images, stamp: up_at(args.image[0], stamp))
        return level, f"leveled by {args.imu}'s up", lambda: ""
    from .frontend.lines import UpTracker

    rig = len(cams) > 1
    track = UpTracker(cams if rig else cams["camera"])
    level = _LevelEachFrame(args, cams, dst, lambda images, stamp: track(images if rig else images[0]))
    return level, "leveled by its own straight lines", lambda: (
        f"; no up found in {track.missed} (each kept the frame before's)" if track.missed else "")


def _frames(args):
    """``(images, stamp in ns or None)`` of each frame of ``args.image``: videos read
    together (one per camera, or one cut by ``--split``), or a ROS bag's ``--topic`` (a
    rig's: one topic per camera, frames matched by stamp), every ``args.every``-th; stops
    at the shortest."""
    from .bags import frames, is_bag, rig_frames
    from .cameras import load_rig

    if is_bag(args.image[0]):
        topics = _bag_topics(args)
        if len(topics) > 1:
            for f in rig_frames(args.image[0], topics, args.every, round(args.max_skew * 1e6)):
                yield f.images, f.stamps_ns[0]
        else:
            for f in frames(args.image[0], topics[0], args.every):
                yield [f.image], f.stamp_ns
        return
    streams = [video_frames(p, args.every, args.eye) for p in args.image]
    count = len(load_rig(args.camera, key=args.key)) if args.split else None
    for frame in zip(*streams):
        images = [im for _, im in frame]
        yield (split_frame(images[0], count, args.camera) if args.split else images), None


def _bag_topics(args) -> list:
    """A bag's image topics to read: ``--topic``'s; else a Kalibr camchain's ``rostopic``s
    when ``--camera`` is one of several cameras and ``--key`` picks none; else the bag's
    only image topic (``[None]``)."""
    if args.topic:
        return args.topic
    if args.camera is not None and args.key is None:
        from .cameras import rig_topics

        found = rig_topics(args.camera)
        if found and len(found) > 1:
            return found
    return [None]


def _frame_rate(args, header_fps: float, first, second) -> float:
    """``--fps``, else the source's: a video's header's (``header_fps``; 0: none), a bag's
    from its first two frames' stamps; 30 where neither says (and it is said)."""
    if args.fps:
        return args.fps
    fps = header_fps / args.every
    if first[1] is not None and second is not None and second[1] > first[1]:
        fps = 1e9 / (second[1] - first[1])
    if fps <= 0:
        print(f"{args.image[0]} gives no frame rate: writing 30 fps (--fps sets it)")
    return fps if fps > 0 else 30.0


def _render_video(args) -> None:
    """``render`` of videos or a ROS bag: the geometry built on the first frame (leveled
    there with ``--level``) and every frame re-imaged through it, written to ``--out``."""
    from tqdm.auto import tqdm

    from .bags import is_bag
    from .viz import FrameVideo

    if len(args.image) > 1 and args.split:
        raise ValueError("--split cuts one video's frames into the rig's cameras' images; give one")
    if Path(args.out).suffix.lower() not in FrameVideo.CODECS:
        raise ValueError(f"--out {args.out}: a video's frames go to a video, .mp4 or .avi")
    frames = _frames(args)
    first = next(frames, None)
    if first is None:  # a bag's topic without a message, or a rig's without one matched set
        raise ValueError(f"{args.image[0]} gave no frame to re-image (with --every "
                         f"{args.every}); check the topic with: usf-graph bag {args.image[0]}")
    second = next(frames, None)
    camera = None
    if args.camera is None:  # a bag's camera_info
        from .cli_bags import bag_camera

        camera = bag_camera(args.image[0], _bag_topics(args)[0], args)
    cams, dst = _sources(args, first[0], camera)
    each = args.imu is not None or args.level_each
    if each:
        level, how, missed = _level_each(args, cams, dst)
        reimage = level
        print(f"{', '.join(cams)} -> {type(dst).__name__} {dst.width}x{dst.height}, each frame "
              f"{how}")
    else:
        one, what = _reimager(args, cams, dst)
        reimage = lambda images, stamp: one(images)  # noqa: E731
        print(what)
    header_fps, count = (0.0, 0) if is_bag(args.image[0]) else video_info(args.image[0])
    video = FrameVideo(args.out, _frame_rate(args, header_fps, first, second))
    total = -(-count // args.every) if count else None
    rest = chain([first], [] if second is None else [second], frames)
    try:
        for images, stamp in tqdm(rest, total=total, desc="re-imaging frames", unit="frame"):
            video.add(reimage(images, stamp))
    finally:
        video.close()
    if each:
        print(f"up {min(level.tilts):.1f} to {max(level.tilts):.1f} degrees off level; the "
              f"geometry built {level.builds} times for {video.frames} frames (up moved more "
              f"than {level.step:g} degrees){missed()}")
    print(f"wrote {args.out} ({video.frames} frames at {video.fps:g} fps)")
    _mark_360(args.out, dst, (".mp4",), "video")


def cmd_render(args) -> int:
    import cv2
    import numpy as np

    from .bags import is_bag

    videos = [p for p in args.image if is_video(p)]
    bag = any(is_bag(p) for p in args.image)
    if videos and len(videos) < len(args.image):
        raise ValueError("give images or videos, not both: a video's frames are re-imaged "
                         "with the video's other cameras' frames")
    if bag and len(args.image) > 1:
        raise ValueError("give one ROS bag (a rig's: --topic once per camera, in the rig's order)")
    if args.topic and not bag:
        raise ValueError("--topic picks a ROS bag's image topic; no bag was given")
    if args.camera is None and not bag:
        raise ValueError("give the camera's calibration with --camera (only a ROS bag can "
                         "bring its own, as camera_info)")
    if args.camera is None and len(args.topic or []) > 1:
        raise ValueError("a rig's bag: give the rig's calibration with --camera")
    if args.imu is not None and (not bag or args.level or args.up is not None):
        raise ValueError("--imu levels each frame of a ROS bag by its IMU's up: a bag, and not "
                         "with --level or --up")
    if args.level_each and (not (videos or bag) or args.level or args.up is not None
                            or args.imu is not None):
        raise ValueError("--level-each levels each frame of a video or a ROS bag by its own "
                         "lines: videos or a bag, and not with --level, --up or --imu")
    if args.imu is None and args.imu_up != "accel":
        raise ValueError("--imu-up says how to read --imu's messages: give --imu TOPIC")
    if args.every != 1 and not (videos or bag):
        raise ValueError("--every picks a video's or a bag's frames; none was given")
    check_panorama_videos(args)
    if videos or bag:
        _render_video(args)
        return 0
    images = read_images(args)
    cams, dst = _sources(args, images)
    reimage, what = _reimager(args, cams, dst)
    out = reimage(images)
    print(what)
    if out.ndim == 3 and out.shape[2] in (3, 4):
        out = cv2.cvtColor(out, cv2.COLOR_RGB2BGR if out.shape[2] == 3 else cv2.COLOR_RGBA2BGRA)
    if args.out.endswith(".npy"):
        np.save(args.out, out)
    else:
        write_image(args.out, out)
    print(f"wrote {args.out}")
    _mark_360(args.out, dst, (".jpg", ".jpeg"), "photo")
    return 0


def _mark_360(out, dst, suffixes: tuple, what: str) -> None:
    """Marks ``out`` as a 360 ``what`` (photo or video) where ``dst`` is a whole
    equirectangular panorama and the file's suffix (one of ``suffixes``) can hold the mark."""
    if getattr(dst, "model", None) != "equirectangular" or not dst.whole_sphere:
        return
    if Path(out).suffix.lower() not in suffixes:
        print(f"a {Path(out).suffix} file holds no 360 {what} metadata that viewers read: write "
              f"{suffixes[0]} for 360 viewers to show it as a sphere")
        return
    from .fileio import mark_360_photo
    from .videos import mark_spherical

    (mark_360_photo if what == "photo" else mark_spherical)(out)
    print(f"marked as a 360 {what}: 360 viewers (YouTube, Google Photos, VLC, ...) show it as a sphere")
