"""Video files: their frames decoded one at a time (OpenCV), their frame rate, and a frame
that holds a rig's cameras side by side cut into their images."""

from __future__ import annotations

from pathlib import Path

#: Files read as videos, frame by frame.
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v")


def is_video(path) -> bool:
    """Whether ``path`` is named as a video (:data:`VIDEO_SUFFIXES`)."""
    return Path(path).suffix.lower() in VIDEO_SUFFIXES


def frames(path, every: int = 1):
    """``(index, RGB frame [H, W, 3] uint8)`` of every ``every``-th frame of the video
    ``path``, decoded one at a time so that a long video never sits in memory."""
    import cv2

    if int(every) != every or every < 1:
        raise ValueError(f"every must be a positive whole number, got {every}")
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise ValueError(f"cannot read video {path}: missing, or a codec OpenCV lacks; "
                         "extract its frames as images instead")
    i = taken = 0
    try:
        while True:
            ok, bgr = cap.read()
            if not ok:
                break
            if i % every == 0:
                taken += 1
                yield i, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            i += 1
    finally:
        cap.release()
    if not taken:
        raise ValueError(f"video {path} has no frames OpenCV can decode")


def info(path) -> tuple[float, int]:
    """``(frames per second, frame count)`` of a video as its header gives them (0 where it
    does not)."""
    import cv2

    cap = cv2.VideoCapture(str(path))
    try:
        return float(cap.get(cv2.CAP_PROP_FPS) or 0.0), int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
    finally:
        cap.release()


def split_frame(image, count: int, what: str) -> list:
    """``image [H, W, ...]`` cut along its width into ``count`` equal images, left to right:
    the cameras of a rig (``what``, for the errors) whose frames hold them side by side, as
    a dual-fisheye 360 camera's do."""
    w = image.shape[1]
    if count < 2:
        raise ValueError(f"splitting cuts a frame into a rig's cameras' images; {what} has one "
                         "camera: leave the split out")
    if w % count:
        raise ValueError(f"the frame is {w} pixels wide, which does not cut into {count} equal "
                         f"parts, one per camera of {what}")
    return [image[:, k * w // count:(k + 1) * w // count] for k in range(count)]


__all__ = ["VIDEO_SUFFIXES", "is_video", "frames", "info", "split_frame"]
