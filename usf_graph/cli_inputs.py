"""What the commands that read a user's camera and images share: the camera from a
calibration file or a panorama spec (and a rig of cameras), its options, and the image."""

from __future__ import annotations

from pathlib import Path

CAMERA_HELP = ("calibration file: Kalibr camchain, Basalt calibration JSON, ORB-SLAM3 "
               "settings, OpenCV FileStorage (incl. fisheye_model "
               "and cv2.omnidir), K/D/DIM, ROS camera_info, USF sensor YAML, OCamCalib "
               "calib_results.txt, lens normal map .npy/.npz, usf-graph YAML, COLMAP "
               "cameras.txt/.bin or a sparse model's folder; or "
               "'equirectangular' (size from the image) / 'equirectangular:WxH'")


def camera_options(p, mask: bool = True) -> None:
    """``--key``, ``--fov`` and (with ``mask``) ``--image-mask``."""
    p.add_argument("--key", default=None, metavar="CAM",
                   help="camera of a Kalibr camchain, Basalt calibration or ORB-SLAM3 stereo "
                        "pair (default: the first: cam0, Camera1) or the id "
                        "of a COLMAP camera (needed when the list has several)")
    p.add_argument("--fov", type=float, default=None, metavar="DEG",
                   help="usable field of view in degrees, about the optical axis (default: "
                        "all the calibration models: a 190-degree fisheye calibrated as "
                        "Kannala-Brandt may claim 270)")
    if mask:
        p.add_argument("--image-mask", default=None, metavar="PNG",
                       help="image whose zero pixels are ignored (vignetting, the robot's "
                            "body, NaN pixels)")


def camera_from_spec(spec: str, key=None, fov=None, image_mask=None, image_shape=None):
    """A camera from a calibration file or ``equirectangular[:WxH]`` (size from the image)."""
    from . import cameras

    if spec.split(":")[0].lower() in ("equirectangular", "panorama"):
        if key is not None:
            raise ValueError("--key picks a camera in a Kalibr, Basalt or COLMAP file; a "
                             "panorama has none")
        size = spec.partition(":")[2]
        if size:
            try:
                w, h = (int(v) for v in size.lower().split("x"))
            except ValueError:
                raise ValueError(f"bad panorama size {size!r}: write equirectangular:WIDTHxHEIGHT, "
                                 "e.g. equirectangular:2048x1024") from None
        elif image_shape is not None:
            h, w = image_shape[:2]
        else:
            raise ValueError("give the panorama's size: equirectangular:WIDTHxHEIGHT")
        return cameras.with_fov_and_mask(cameras.Equirectangular(w, h), fov, image_mask)
    return cameras.load(spec, key=key, fov_deg=fov, image_mask=image_mask)


def rig_from_spec(spec: str, fov=None, image_mask=None) -> dict:
    """Every camera of a Kalibr camchain or Basalt calibration, mounted in the rig, each with the usable field of
    view and image mask given."""
    from . import cameras

    return {n: cameras.with_fov_and_mask(c, fov, image_mask)
            for n, c in cameras.load_rig(spec).items()}


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
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"cannot read image {p}: missing, or not an image format OpenCV reads")
    if img.ndim == 3 and img.shape[2] in (3, 4):  # OpenCV's BGR(A) -> RGB(A)
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB if img.shape[2] == 3 else cv2.COLOR_BGRA2RGBA)
    return img
