"""Video files: their frames decoded one at a time (OpenCV), their frame rate, a frame that
holds a rig's cameras side by side cut into their images, a stereo 360 video's frame cut
into one eye's, and the 360 video metadata of an MP4 read and written."""

from __future__ import annotations

import warnings
from pathlib import Path

#: Files read as videos, frame by frame (``.insv``: an Insta360 camera's MP4, one lens or
#: both side by side).
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".insv")


def is_video(path) -> bool:
    """Whether ``path`` is named as a video (:data:`VIDEO_SUFFIXES`)."""
    return Path(path).suffix.lower() in VIDEO_SUFFIXES


def check_every(every) -> int:
    """``every`` (keep every ``every``-th frame) as an int, where it is a positive whole
    number."""
    if int(every) != every or every < 1:
        raise ValueError(f"every must be a positive whole number, got {every}")
    return int(every)


def frames(path, every: int = 1, eye: str | None = None):
    """``(index, RGB frame [H, W, 3] uint8)`` of every ``every``-th frame of the video
    ``path``, decoded one at a time so that a long video never sits in memory; with ``eye``
    (``"left"`` or ``"right"``), of a stereo 360 video, that eye's part of each frame
    (:func:`eye_image`, the layout from its metadata: :func:`stereo_layout`)."""
    import cv2

    check_every(every)
    layout = None if eye is None else stereo_layout(path, eye)
    tracks = video_track_count(path)
    if tracks > 1:  # rather than read one lens of several without a word
        warnings.warn(f"{path} holds {tracks} video tracks (an Insta360 file: one per lens); "
                      "OpenCV decodes the first only. To read another, copy it out: ffmpeg "
                      f"-i {path} -map 0:v:1 -c copy track1.mp4", stacklevel=2)
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
                rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
                yield i, rgb if layout is None else eye_image(rgb, layout, eye)
            i += 1
    finally:
        cap.release()
    if not taken:
        raise ValueError(f"video {path} has no frames OpenCV can decode")


#: Where each eye's panorama lies in a stereo frame, by the layout its metadata names:
#: (the axis the frame is cut along, 0 rows or 1 columns; the left eye's half, 0 or 1).
STEREO_LAYOUTS = {"top-bottom": (0, 0), "left-right": (1, 0), "right-left": (1, 1)}
EYES = ("left", "right")


def eye_image(image, layout: str, eye: str):
    """One eye's half of a stereo frame ``image [H, W, ...]``: ``layout`` is
    :data:`STEREO_LAYOUTS`' (``top-bottom``: the left eye on top, as the Spherical Video
    RFC has it)."""
    _check_eye(eye)
    if layout not in STEREO_LAYOUTS:
        raise ValueError(f"stereo layout {layout!r} cannot be cut into its eyes: one of "
                         f"{', '.join(STEREO_LAYOUTS)}")
    axis, left = STEREO_LAYOUTS[layout]
    n = image.shape[axis]
    if n % 2:
        raise ValueError(f"a {layout} stereo frame must have an even {'height' if axis == 0 else 'width'}, "
                         f"got {n} pixels")
    half = left if eye == "left" else 1 - left
    cut = slice(half * n // 2, (half + 1) * n // 2)
    return image[cut] if axis == 0 else image[:, cut]


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


#: The files that hold 360 video metadata: MP4 (Insta360's too) and QuickTime.
_MP4_SUFFIXES = (".mp4", ".m4v", ".mov", ".insv")
#: The Spherical Video (V1) metadata box, ``moov.trak.uuid`` with this UUID, holding XML
#: (google/spatial-media's RFC; what YouTube, VLC and FFmpeg read).
SPHERICAL_UUID = bytes.fromhex("ffcc8263f8554a938814587a02521fdd")
_SPHERICAL_XML = (
    '<?xml version="1.0"?><rdf:SphericalVideo '
    'xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#" '
    'xmlns:GSpherical="http://ns.google.com/videos/1.0/spherical/">'
    "<GSpherical:Spherical>true</GSpherical:Spherical>"
    "<GSpherical:Stitched>true</GSpherical:Stitched>"
    "<GSpherical:StitchingSoftware>{software}</GSpherical:StitchingSoftware>"
    "<GSpherical:ProjectionType>equirectangular</GSpherical:ProjectionType>"
    "<GSpherical:StereoMode>{stereo}</GSpherical:StereoMode>"
    "</rdf:SphericalVideo>")


def _boxes(read, start: int, end: int, where) -> list:
    """``[(offset, size, header size, type)]`` of the ISO BMFF boxes in bytes ``[start,
    end)``, ``read(offset, n)`` giving the bytes (of a file or of memory)."""
    out, i = [], start
    while i < end:
        h = read(i, 16)
        size, kind, head = int.from_bytes(h[:4], "big"), h[4:8], 8
        if size == 1 and len(h) == 16:
            size, head = int.from_bytes(h[8:16], "big"), 16
        elif size == 0:  # to the end of its parent
            size = end - i
        if len(h) < 8 or size < head or i + size > end:
            raise ValueError(f"{where}: the box at byte {i} runs past its parent: the file is "
                             "corrupt, cut short or not an MP4")
        out.append((i, size, head, kind))
        i += size
    return out


def _children(box: bytes, head: int, where) -> list:
    """The child boxes of ``box`` (its header ``head`` bytes long): ``[(type, bytes, header
    size)]``."""
    return [(k, box[o:o + s], h) for o, s, h, k in
            _boxes(lambda o, n: box[o:o + n], head, len(box), where)]


def _rebuilt(box: bytes, head: int, children: list) -> bytes:
    """``box``'s first ``head`` bytes (its header, and any fields before its children), then
    ``children`` (as :func:`_children` gives them), its size set anew (32 or 64 bits, as it
    was)."""
    out = box[:head] + b"".join(b for _, b, _ in children)
    if box[:4] == b"\0\0\0\x01":  # a 64-bit size after the type
        return out[:8] + len(out).to_bytes(8, "big") + out[16:]
    if len(out) >= 1 << 32:
        raise ValueError("a box outgrew a 32-bit size: the video is too large to mark")
    return len(out).to_bytes(4, "big") + out[4:]


def _is_video_track(trak: bytes, head: int, where) -> bool:
    """Whether the ``trak`` box's handler (``mdia.hdlr``) is ``vide``."""
    return any(b[h + 8:h + 12] == b"vide"  # after version and pre_defined
               for b, h in _find(trak, head, (b"mdia", b"hdlr"), where))


def _shifted(box: bytes, head: int, after: int, delta: int, where) -> bytes:
    """``box`` with every chunk offset under it (``stco``, ``co64``) at or past byte
    ``after`` moved by ``delta``: the media data moves when a box before it grows."""
    kind = box[4:8]
    if kind in (b"stco", b"co64"):
        width = 4 if kind == b"stco" else 8
        n = int.from_bytes(box[head + 4:head + 8], "big")
        end = head + 8 + n * width
        if end > len(box):
            raise ValueError(f"{where}: a chunk offset table is cut short: the file is corrupt")
        offs = [int.from_bytes(box[k:k + width], "big") for k in range(head + 8, end, width)]
        offs = [o + delta if o >= after else o for o in offs]
        if width == 4 and max(offs, default=0) >= 1 << 32:
            raise ValueError(f"{where}: the media data would move past 4 GiB: too large to mark")
        return box[:head + 8] + b"".join(o.to_bytes(width, "big") for o in offs) + box[end:]
    if kind in (b"moov", b"trak", b"mdia", b"minf", b"stbl"):
        return _rebuilt(box, head, [(k, _shifted(b, h, after, delta, where), h)
                                    for k, b, h in _children(box, head, where)])
    return box


def _copy(src, out, start: int, end: int) -> None:
    """Bytes ``[start, end)`` of the open file ``src`` to ``out``, 16 MiB at a time."""
    src.seek(start)
    while start < end:
        chunk = src.read(min(1 << 24, end - start))
        if not chunk:
            raise ValueError("the video was cut short while it was being marked")
        out.write(chunk)
        start += len(chunk)


#: The text an Insta360 file ends with: its trailer (IMU, exposure, lens data) follows the
#: boxes, its footer (72 bytes: 32 reserved, the trailer's size from its start to the end
#: as a little-endian u32, a u32 version, then this) at the very end.
INSTA360_MAGIC = b"8db42d694ccc418790edff439fe026bf"


def _boxes_end(read, length: int) -> int:
    """Where the MP4's boxes end: before an Insta360 trailer, else at ``length``."""
    if length < 72 or read(length - 32, 32) != INSTA360_MAGIC:
        return length
    size = int.from_bytes(read(length - 40, 4), "little")
    return length - size if 72 <= size <= length else length


def _moov(path) -> tuple[int, int, int, bytes]:
    """The MP4 ``path``'s one ``moov`` box: ``(offset, size, header size, its bytes)``."""
    length = Path(path).stat().st_size
    with open(path, "rb") as f:
        def read(o, n):
            f.seek(o)
            return f.read(n)

        end = _boxes_end(read, length)
        moovs = [b for b in _boxes(read, 0, end, str(path)) if b[3] == b"moov"]
        if len(moovs) != 1:
            raise ValueError(f"{path}: {len(moovs)} moov boxes, not one: not a finished MP4")
        start, size, head, _ = moovs[0]
        return start, size, head, read(start, size)


def mark_spherical(path, software: str = "usf-graph", stereo: str = "mono") -> None:
    """Marks the MP4 video ``path``, whose frames are whole equirectangular panoramas, as a
    360 video: the Spherical Video (V1) metadata, a ``uuid`` box in its video track, so that
    YouTube, VLC and other 360 players show it as a sphere. ``stereo``: ``mono``, or
    ``top-bottom`` / ``left-right`` for frames holding one panorama per eye. Marking again
    replaces the mark. The file is rewritten atomically; the frames are not touched."""
    from .fileio import atomic_write

    path = Path(path)
    where = str(path)
    if path.suffix.lower() not in _MP4_SUFFIXES:
        raise ValueError(f"{where}: only MP4 (and QuickTime) files hold 360 video metadata; "
                         "write .mp4")
    if stereo not in ("mono", "top-bottom", "left-right"):
        raise ValueError(f"stereo must be mono, top-bottom or left-right, got {stereo!r}")
    start, size, head, moov = _moov(path)
    length = path.stat().st_size
    xml = _SPHERICAL_XML.format(software=software, stereo=stereo).encode()
    uuid = (24 + len(xml)).to_bytes(4, "big") + b"uuid" + SPHERICAL_UUID + xml
    children = _children(moov, head, where)
    video = [k == b"trak" and _is_video_track(b, h, where) for k, b, h in children]
    if not any(video):
        raise ValueError(f"{where}: no video track to mark")
    for i in [i for i, v in enumerate(video) if v]:
        _, trak, h = children[i]
        kept = [c for c in _children(trak, h, where)
                if not (c[0] == b"uuid" and c[1][c[2]:c[2] + 16] == SPHERICAL_UUID)]
        children[i] = (b"trak", _rebuilt(trak, h, [*kept, (b"uuid", uuid, 8)]), h)
    new = _rebuilt(moov, head, children)
    if len(new) != size:  # the media data after the moov box moves
        new = _shifted(new, head, start + size, len(new) - size, where)

    def write(out):
        with open(path, "rb") as f:
            _copy(f, out, 0, start)
            out.write(new)
            _copy(f, out, start + size, length)

    atomic_write(path, write)


#: Spherical Video V2's ``st3d`` stereo modes.
_STEREO_MODES = {0: "mono", 1: "top-bottom", 2: "left-right", 3: "stereo-custom", 4: "right-left"}
_PROJECTIONS = {b"equi": "equirectangular", b"cbmp": "cubemap", b"mesh": "mesh"}
_VISUAL_SAMPLE_ENTRY = 78  # bytes of a video sample entry's fields before its child boxes


def _video_tracks(path) -> list:
    """The video ``trak`` boxes of the MP4 ``path`` with their header sizes; ``[]`` where
    it is no MP4 (or not one this reader follows)."""
    where = str(path)
    try:
        _, _, head, moov = _moov(path)
    except ValueError:
        return []
    return [(trak, h) for kind, trak, h in _children(moov, head, where)
            if kind == b"trak" and _is_video_track(trak, h, where)]


def _video_track(path) -> tuple[bytes, int] | None:
    """The first video ``trak`` box of the MP4 ``path`` and its header size, or None."""
    return next(iter(_video_tracks(path)), None)


def video_track_count(path) -> int:
    """How many video tracks the MP4 ``path`` holds (0 where it is no MP4): an Insta360
    file may hold one per lens, of which OpenCV decodes the first."""
    if Path(path).suffix.lower() not in _MP4_SUFFIXES:
        return 0
    return len(_video_tracks(path))


def _find(box: bytes, head: int, path: tuple, where) -> list:
    """The boxes at ``path`` (types, from ``box``'s children down) as ``(bytes, header)``."""
    found = [(box, head)]
    for kind in path:
        found = [(b, h) for parent, ph in found for k, b, h in _children(parent, ph, where)
                 if k == kind]
    return found


def spherical_metadata(path) -> dict | None:
    """What the 360 video metadata of the MP4 ``path`` says of its video:
    ``{"projection": ..., "stereo": ..., "version": 1 or 2}``, from the Spherical Video V2
    boxes (``st3d``, ``sv3d``) or else the V1 XML (:func:`mark_spherical`); None where it
    has none, or the file is no MP4."""
    from .fileio import xml_fields

    if Path(path).suffix.lower() not in _MP4_SUFFIXES:
        return None
    found = _video_track(path)
    if found is None:
        return None
    trak, head = found
    where = str(path)
    entries = _find(trak, head, (b"mdia", b"minf", b"stbl", b"stsd"), where)
    for stsd, h in entries:  # its first sample entry's children: st3d, sv3d
        entry = _children(stsd, h + 8, where)[:1]  # after the version, flags and entry count
        for _, box, eh in entry:
            kids = {k: (b, hh) for k, b, hh in _children(box, eh + _VISUAL_SAMPLE_ENTRY, where)}
            if b"sv3d" in kids or b"st3d" in kids:
                stereo = "mono"
                if b"st3d" in kids:
                    b, hh = kids[b"st3d"]
                    stereo = _STEREO_MODES.get(b[hh + 4], f"mode {b[hh + 4]}")
                projection = "equirectangular"
                if b"sv3d" in kids:  # sv3d.proj: a header (prhd), then the projection's box
                    kinds = [k for proj, ph in _find(*kids[b"sv3d"], (b"proj",), where)
                             for k, _, _ in _children(proj, ph, where) if k != b"prhd"]
                    projection = _PROJECTIONS.get(kinds[0], "unknown") if kinds else "unknown"
                return {"projection": projection, "stereo": stereo, "version": 2}
    for kind, box, h in _children(trak, head, where):
        if kind == b"uuid" and box[h:h + 16] == SPHERICAL_UUID:
            get = xml_fields(box[h + 16:], "http://ns.google.com/videos/1.0/spherical/")
            if get is None:
                return None
            return {"projection": get.get("ProjectionType", "equirectangular").lower(),
                    "stereo": get.get("StereoMode", "mono").lower(), "version": 1}
    return None


def stereo_layout(path, eye: str) -> str:
    """The stereo layout (:data:`STEREO_LAYOUTS`) that the 360 video metadata of ``path``
    gives, for cutting out ``eye``; raises where it says none (mono, or no metadata)."""
    _check_eye(eye)  # before the file is read
    return _stereo_layout(path, eye, spherical_metadata(path))


def _check_eye(eye: str) -> None:
    if eye not in EYES:
        raise ValueError(f"eye must be 'left' or 'right', got {eye!r}")


def _stereo_layout(path, eye: str, meta: dict | None) -> str:
    """:func:`stereo_layout` from the metadata already read (``meta``)."""
    _check_eye(eye)
    if meta is None or meta["stereo"] == "mono":
        said = "no 360 video metadata" if meta is None else "360 video metadata that says mono"
        raise ValueError(f"{path} has {said}: picking an eye ({eye}) is for a stereo 360 "
                         "video; leave it out, or for a stereo video written without metadata, "
                         "cut the eye out first (e.g. FFmpeg's crop filter)")
    if meta["stereo"] not in STEREO_LAYOUTS:
        raise ValueError(f"{path}: its 360 video metadata says stereo layout {meta['stereo']}, "
                         f"which cannot be cut into its eyes (known: {', '.join(STEREO_LAYOUTS)})")
    return meta["stereo"]


def check_panorama_video(path, eye: str | None = None) -> None:
    """Raises where the 360 video metadata of ``path`` says that its frames are no single
    equirectangular panorama (a cube map's are faces; a stereo video's hold one per eye,
    unless ``eye`` picks one, as :func:`frames` cuts it), so that reading them as one is
    refused rather than silently wrong."""
    meta = spherical_metadata(path)
    if meta is not None and meta["projection"] != "equirectangular":
        hint = {"cubemap": "if its frames are FFmpeg's 3x2 cube map, read them with --camera "
                           "cubemap:c3x2; else ",
                "mesh": "if it is YouTube's equi-angular cube map (EAC, which YouTube's streams "
                        "mark with a mesh), read it with --camera eac; else "}.get(meta["projection"], "")
        raise ValueError(f"{path}: its 360 video metadata (V{meta['version']}) says projection "
                         f"{meta['projection']}, not equirectangular: {hint}re-encode it to an "
                         "equirectangular panorama first (e.g. FFmpeg's v360 filter)")
    if eye is not None:
        _stereo_layout(path, eye, meta)
    elif meta is not None and meta["stereo"] != "mono":
        raise ValueError(f"{path}: its 360 video metadata (V{meta['version']}) says it is stereo "
                         f"({meta['stereo']}): each frame holds one panorama per eye; pick one "
                         "(the command line's --eye left or --eye right; in Python, eye=)")
