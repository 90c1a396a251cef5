"""What the commands that read a user's camera and images share: the camera from a
calibration file or a panorama spec (and a rig of cameras), its options, and the image."""

from __future__ import annotations

from pathlib import Path

CAMERA_HELP = ("calibration file: Kalibr camchain, Basalt calibration JSON, ORB-SLAM3 "
               "settings, OpenCV FileStorage (incl. fisheye_model "
               "and cv2.omnidir), K/D/DIM, ROS camera_info, USF sensor or VINS-Fusion YAML, "
               "OCamCalib calib_results.txt, lens normal map .npy/.npz, usf-graph YAML, COLMAP "
               "cameras.txt/.bin or a sparse model's folder, nerfstudio transforms.json, "
               "WoodScape calibration JSON (a rig: its cameras' files, comma-separated); or "
               "'equirectangular' (size from the image) / 'equirectangular:WxH'; or "
               "'cubemap' (a 6:1 horizon strip or a 4:3 dice cross, from the image) / "
               "'cubemap:SIZE[:horizon|dice|c6x1|c3x2]' (six faces, SIZE pixels square); or "
               "'eac' / 'eac:WxH' (YouTube's equi-angular cube map, as FFmpeg's v360 eac)")


def camera_options(p, mask: bool = True) -> None:
    """``--key``, ``--fov`` and (with ``mask``) ``--image-mask``."""
    p.add_argument("--key", default=None, metavar="CAM",
                   help="camera of a Kalibr camchain, Basalt calibration or ORB-SLAM3 stereo "
                        "pair (default: the first: cam0, Camera1) or the id "
                        "of a COLMAP camera (needed when the list has several); with a rig "
                        "(--rig, or several images to lift) the id of a COLMAP rig, needed "
                        "when the model holds several")
    p.add_argument("--fov", type=float, default=None, metavar="DEG",
                   help="usable field of view in degrees, about the optical axis (default: "
                        "all the calibration models: a 190-degree fisheye calibrated as "
                        "Kannala-Brandt may claim 270)")
    if mask:
        p.add_argument("--image-mask", default=None, metavar="PNG",
                       help="image whose zero pixels are ignored (vignetting, the robot's "
                            "body, NaN pixels)")


def level_options(p, what: str) -> None:
    """``--level`` (doing ``what``) and ``--up X Y Z``."""
    p.add_argument("--level", action="store_true",
                   help=f"level the view: {what}, keeping its heading. Up from the image's "
                        "straight lines (walls, doors, shelves: the camera held within 40 "
                        "degrees of upright; reliable on panoramas, less so through narrow "
                        "views: check the result; a rig's cameras' lines together), or --up")
    p.add_argument("--up", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                   help="with --level: up in the source camera's (or rig's) sphere frame "
                        "(x forward, y left, z up), e.g. from an IMU")


def leveled(cam, image, args):
    """``cam`` mounted in a level frame, where ``args.level``: turned by the smallest rotation
    that takes up (``args.up``, else from the straight lines of ``image``, which ``cam``
    took) to +z (:func:`usf_graph.geometry.level_rotation`), with what was found printed.
    A rig's cameras (a dict, ``image`` a list of their images) are turned together, up read
    from all their lines, in the rig's frame. As it is otherwise (and ``--up`` alone
    refused)."""
    if not args.level:
        if args.up is not None:
            raise ValueError("--up says where up is for --level: add --level")
        return cam
    import numpy as np

    from .frontend.lines import lines_up
    from .geometry import geodesic_distance, level_rotation

    u = lines_up(image, cam) if args.up is None else np.asarray(args.up, np.float64)
    R = level_rotation(u)
    u = u / np.linalg.norm(u)
    rig = isinstance(cam, dict)
    print(f"up {'given' if args.up is not None else 'from the straight lines'}: "
          f"({u[0]:.4f}, {u[1]:.4f}, {u[2]:.4f}) in the {'rig' if rig else 'camera'}'s sphere "
          f"frame, which is {np.degrees(geodesic_distance(u, [0.0, 0.0, 1.0])):.1f} degrees off level")
    return {n: c.turned(R) for n, c in cam.items()} if rig else cam.turned(R)


def is_panorama_spec(spec: str) -> bool:
    """``equirectangular`` or ``panorama``, with or without ``:WxH``."""
    return spec.split(":")[0].lower() in ("equirectangular", "panorama")


def eye_option(p) -> None:
    """``--eye``: one eye of a stereo 360 video (:func:`usf_graph.videos.eye_image`)."""
    from .videos import EYES

    p.add_argument("--eye", default=None, choices=EYES,
                   help="stereo 360 videos: read this eye's panorama of each frame (where "
                        "the video's 360 metadata says top-bottom or left-right)")


def check_panorama_videos(args) -> None:
    """``--camera equirectangular`` on videos: refused where a video's 360 metadata says its
    frames are no single equirectangular panorama (a cube map; stereo, unless ``--eye``
    picks one); ``--eye`` refused where a video's metadata says no stereo layout."""
    from .videos import check_panorama_video, is_video, stereo_layout

    videos = [p for p in args.image if is_video(p)]
    if args.eye is not None and len(videos) < len(args.image):
        raise ValueError("--eye picks one eye of a stereo 360 video's frames: give videos")
    panorama = args.camera is not None and is_panorama_spec(args.camera)
    for path in videos:
        if panorama:
            check_panorama_video(path, args.eye)
        elif args.eye is not None:
            stereo_layout(path, args.eye)


def has_size(spec: str) -> bool:
    """Whether a panorama's or a cube map's spec gives its size (``:WxH``, ``:SIZE``)."""
    return any(p[:1].isdigit() for p in spec.split(":")[1:])


def is_cubemap_spec(spec: str) -> bool:
    """``cubemap``, with or without ``:SIZE`` and ``:LAYOUT``, or ``eac`` with or without
    ``:WxH``."""
    return spec.split(":")[0].lower() in ("cubemap", "eac")


def _cubemap(spec: str, image_shape):
    """The :class:`~usf_graph.cameras.Cubemap` of ``cubemap[:SIZE][:LAYOUT]``; without a
    size, the image's (``image_shape``: 6:1 a horizon strip, 4:3 a dice cross; other
    layouts of those shapes, and the 3:2 ones, by name). ``eac[:WxH]``: the
    :class:`~usf_graph.cameras.EquiAngularCubemap` of that size, else the image's."""
    from .cameras import Cubemap, EquiAngularCubemap
    from .cameras.cubemap import LAYOUTS

    if spec.split(":")[0].lower() == "eac":
        size = spec.partition(":")[2]
        if size:
            return EquiAngularCubemap(*image_size(size, "EAC image size", "eac:3072x2048"))
        if image_shape is None:
            raise ValueError("give the equi-angular cube map's size: eac:WIDTHxHEIGHT")
        return EquiAngularCubemap(image_shape[1], image_shape[0])
    parts = [p.lower() for p in spec.split(":")[1:] if p]
    layouts, sizes = [p for p in parts if p in LAYOUTS], [p for p in parts if p not in LAYOUTS]
    if len(layouts) > 1 or len(sizes) > 1 or (sizes and not (sizes[0].isdigit() and int(sizes[0]))):
        raise ValueError(f"{spec!r}: write cubemap[:SIZE][:LAYOUT], e.g. cubemap:512 or "
                         f"cubemap:512:dice (layouts: {', '.join(LAYOUTS)})")
    layout = layouts[0] if layouts else None
    if sizes:
        return Cubemap(int(sizes[0]), layout or "horizon")
    if image_shape is None:
        raise ValueError("give the cube map's face size: cubemap:SIZE")
    h, w = image_shape[:2]
    fits = [k for k, v in LAYOUTS.items() if w * v.shape[1] == h * v.shape[0]]
    if layout is None and fits == ["c3x2"]:  # 3:2: FFmpeg's cube map or YouTube's EAC
        raise ValueError(f"the image is {w}x{h}, 3:2: name its kind, cubemap:c3x2 (FFmpeg's "
                         "cube map) or eac (YouTube's equi-angular one)")
    found = layout if layout in fits else fits[0] if fits and layout is None else None
    if found is None:
        raise ValueError(f"the image is {w}x{h}: a cube map's is 6:1 (horizon, c6x1), 4:3 "
                         "(dice) or 3:2 (c3x2); give its layout and face size, "
                         "cubemap:SIZE:LAYOUT")
    return Cubemap(h // LAYOUTS[found].shape[1], found)


def camera_from_spec(spec: str, key=None, fov=None, image_mask=None, image_shape=None,
                     image_path=None):
    """A camera from a calibration file or ``equirectangular[:WxH]`` (size from the image).
    With ``image_shape``, a calibration made for another size of the same aspect ratio is
    scaled to the image (:meth:`~usf_graph.cameras.Camera.resized`, with a note): a video
    recorded or saved smaller than the calibration images. ``equirectangular`` without a
    size, for a JPEG (``image_path``) whose Photo Sphere XMP says it is cropped (a phone's
    panorama short of the poles), is that crop, with a note. Without ``key``, a calibration
    file whose frames have intrinsics of their own (a ``transforms.json``) gives the
    camera of ``image_path``'s frame (:func:`~usf_graph.cameras.frame_key`)."""
    from . import cameras

    cube, pano = is_cubemap_spec(spec), is_panorama_spec(spec)
    if (cube or pano) and key is not None:
        raise ValueError("--key picks a camera in a Kalibr, Basalt or COLMAP file; a "
                         f"{'cube map' if cube else 'panorama'} has none")
    if cube:
        return cameras.with_fov_and_mask(_cubemap(spec, image_shape), fov, image_mask)
    if pano:
        size = spec.partition(":")[2]
        if size:
            w, h = image_size(size, "panorama size", "equirectangular:2048x1024")
        elif image_shape is not None:
            h, w = image_shape[:2]
            crop = _photo_sphere_crop(image_path, w, h)
            if crop is not None:
                return cameras.with_fov_and_mask(crop, fov, image_mask)
        else:
            raise ValueError("give the panorama's size: equirectangular:WIDTHxHEIGHT")
        return cameras.with_fov_and_mask(cameras.Equirectangular(w, h), fov, image_mask)
    if key is None:  # a transforms.json whose frames have their own intrinsics: the image's
        key = cameras.frame_key(spec, image_path)
    cam = fit_to_image(cameras.load(spec, key=key, fov_deg=fov), image_shape)
    return cameras.with_fov_and_mask(cam, None, image_mask)


def _photo_sphere_crop(path, width: int, height: int):
    """The cropped panorama that ``path``'s Photo Sphere XMP describes, said aloud; None
    where it has none or describes the whole sphere."""
    if path is None or Path(path).suffix.lower() not in (".jpg", ".jpeg"):
        return None
    import math

    from .cameras import Equirectangular
    from .fileio import read_photo_sphere

    gpano = read_photo_sphere(path)
    if not gpano or "FullPanoWidthPixels" not in gpano:
        return None
    cam = Equirectangular.from_photo_sphere(gpano, width, height)
    if cam.whole_sphere:
        return None
    (a, b), (c, d) = cam.lat_range, cam.lon_range
    print(f"{path}: a Photo Sphere cropped to latitudes {math.degrees(a):.1f} to "
          f"{math.degrees(b):.1f} and longitudes {math.degrees(c):.1f} to {math.degrees(d):.1f} "
          "degrees (its XMP); give equirectangular:WxH to read it as the whole sphere")
    return cam


def image_size(text: str, what: str = "image size", example: str = "640x480") -> tuple[int, int]:
    """``WIDTHxHEIGHT`` -> ``(width, height)``, both positive whole numbers."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        w = h = 0
    if w < 1 or h < 1:
        raise ValueError(f"bad {what} {text!r}: write WIDTHxHEIGHT, e.g. {example}")
    return w, h


def fit_to_image(cam, image_shape):
    """``cam`` scaled to an image of another size with the same aspect ratio (a frame
    resized as a whole; :meth:`~usf_graph.cameras.Camera.resized`), with a note; else
    ``cam`` (a crop is the lift's error to report)."""
    if image_shape is None or tuple(image_shape[:2]) == (cam.height, cam.width):
        return cam
    h, w = image_shape[:2]
    if abs(w / cam.width - h / cam.height) >= 0.01 * w / cam.width:
        return cam
    print(f"note: the image is {w}x{h} and the calibration {cam.width}x{cam.height}: scaling "
          f"the calibration by {w / cam.width:.4g} (if the image is a crop, calibrate for it "
          "instead)")
    return cam.resized(w, h)


def rig_options(p, blend: bool = False, split: bool = True) -> None:
    """``--distance``, for the commands that read a rig; with ``blend``, ``--blend``; with
    ``split``, ``--split`` (:func:`usf_graph.videos.split_frame`)."""
    if split:
        p.add_argument("--split", action="store_true",
                       help="rigs: each image (or video frame) holds the rig's cameras' images "
                            "side by side, in its order, of equal widths (a dual-fisheye 360 "
                            "camera's frame)")
    if blend:
        from .frontend.choices import BLENDS

        p.add_argument("--blend", default="best", choices=BLENDS,
                       help="rigs: where cameras overlap, the one looking closest (best) or a "
                            "weighted average (feather)")
    p.add_argument("--distance", type=_distance, default=None, metavar="M",
                   help="with a rig: stitch its cameras at this distance from the rig's centre "
                        "('auto': where the cameras agree best on their overlaps, from the "
                        "images; a rig's bag, from its first frame), "
                        "in the calibration's unit (metres; COLMAP: the model's), so that "
                        "near scenes line up across cameras that are apart (default: at "
                        "infinity, the baseline ignored)")


def _distance(text: str):
    if text == "auto":
        return text
    try:
        return float(text)
    except ValueError:
        import argparse

        raise argparse.ArgumentTypeError(f"a distance in the calibration's unit, or 'auto'; "
                                         f"got {text!r}") from None


def calibration_files(spec: str):
    """``--camera`` as :func:`usf_graph.cameras.load_rig` takes it: comma-separated files of
    one posed camera each as a list, one file as it is."""
    return spec.split(",") if "," in spec else spec


def rig_from_spec(spec: str, fov=None, image_mask=None, key=None, distance=None, images=None,
                  grid=None) -> dict:
    """Every camera of a rig's file, or of comma-separated files of one posed camera each
    (:func:`usf_graph.cameras.load_rig`; ``key``: a COLMAP rig's id), mounted in the rig, each scaled to its image in ``images`` where that is the
    frame resized as a whole (:func:`fit_to_image`), with the usable field of view and
    image mask given, stitched at ``distance`` (:func:`usf_graph.cameras.stitch_at`) where
    given; ``"auto"``: where ``images`` agree best on ``grid`` (icosahedral:5 by default;
    :func:`usf_graph.frontend.choose_distance`)."""
    from . import cameras

    rig = cameras.load_rig(calibration_files(spec), key=key)
    if images is not None and len(images) == len(rig):  # frames resized as a whole
        rig = {n: fit_to_image(c, im.shape) for (n, c), im in zip(rig.items(), images)}
    rig = {n: cameras.with_fov_and_mask(c, fov, image_mask) for n, c in rig.items()}
    if distance == "auto":
        from .frontend import choose_distance
        from .grids import icosahedral

        if images is None:
            raise ValueError("--distance auto chooses from the rig's images, and there are "
                             "none here: give the distance, in the calibration's unit")
        distance, errors = choose_distance(rig, grid or icosahedral(5), images)
        print("stitching distance chosen where the cameras agree best: " +
              ("infinity" if distance is None else f"{distance:.3g}") + " (seam error " +
              ", ".join(f"{'inf' if d is None else f'{d:.3g}'}: {e:.3g}" for d, e in errors.items())
              + ")")
    return cameras.stitch_at(rig, distance) if distance is not None else rig


def read_image(path):
    """An image file (RGB(A) from OpenCV's BGR(A)) or a ``.npy`` array."""
    import cv2
    import numpy as np

    p = Path(path)
    if p.suffix == ".npy":
        try:
            return np.load(p, allow_pickle=False)
        except (OSError, ValueError) as e:
            raise ValueError(f"cannot read image {p}: {e}") from e
    from .bags import is_bag
    from .fileio import EXIF_ORIENTATIONS, decode_image, exif_orientation

    if is_bag(p) and p.exists():
        raise ValueError(f"{p} is a ROS bag, not an image: 'usf-graph predict' reads bags "
                         "(in Python: usf_graph.bags.frames)")
    if not p.is_file():
        raise ValueError(f"image {p} does not exist" + (" (it is a folder)" if p.is_dir() else ""))
    data = p.read_bytes()  # read once, for OpenCV's pixels and Pillow's header
    img = decode_image(data)  # the stored pixels: OpenCV's IMREAD_UNCHANGED applies no EXIF turn
    if img is None:
        raise ValueError(f"cannot read image {p}: empty, or not an image format OpenCV reads")
    turn = EXIF_ORIENTATIONS.get(exif_orientation(data))
    if turn is not None:
        print(f"note: {p.name} is shown {turn} by viewers (its EXIF orientation); usf-graph reads "
              "its pixels as stored, which calibrations from raw frames describe (Kalibr, ROS, "
              "OpenCV). If the camera was calibrated on the turned images, store the image "
              "turned first (PIL.ImageOps.exif_transpose)")
    if img.ndim == 3 and img.shape[2] in (3, 4):  # OpenCV's BGR(A) -> RGB(A)
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB if img.shape[2] == 3 else cv2.COLOR_BGRA2RGBA)
    return img


def alpha_masked(camera, image, path):
    """``camera`` with the pixels that ``image``'s alpha channel makes fully transparent
    masked too (as ``--image-mask`` would); unchanged without alpha or where all is opaque."""
    if image.ndim != 3 or image.shape[2] != 4 or image.shape[:2] != (camera.height, camera.width):
        return camera  # no alpha; a wrong size is the lift's error to report
    opaque = image[..., 3] > 0
    if opaque.all():
        return camera
    print(f"{Path(path).name}: its alpha channel hides {int((~opaque).sum())} pixels; they are "
          "left out")
    return camera.with_image_mask(opaque, combine=True)


def camera_test(args, ckpt, dataset, grid: str):
    """``eval --camera``: the rooms test views of ``ckpt``'s seed and materials seen
    through the user's calibrated camera (``--key``, ``--fov``, ``--image-mask``), as the
    protocol's zero-shot lenses see them (level, along each viewpoint's random yaw; the
    camera's own mounting kept), at its calibrated size, lifted onto ``grid`` as
    ``predict`` would lift it (``area`` for images finer than the grid); None without
    ``--camera``. ``dataset``: :class:`~usf_graph.datasets.RoomsSegmentation` or
    :class:`~usf_graph.datasets.RoomsDetection`."""
    if args.camera is None:
        if args.key is not None or args.fov is not None or args.image_mask is not None:
            raise ValueError("--key, --fov and --image-mask describe --camera's camera: give "
                             "--camera")
        return None
    from .grids import from_spec
    from .train.apply import choose_interpolation

    cam = camera_from_spec(args.camera, args.key, args.fov, args.image_mask)
    print(f"(camera) {cam}")
    return dataset(args.root or "data/rooms", "test", camera=cam, grid=grid, rotate="none",
                   num_scenes=args.num_test or 50, seed=ckpt.rooms_seed(args.seed),
                   materials=ckpt.materials,
                   interpolation=choose_interpolation(cam, from_spec(grid)))
