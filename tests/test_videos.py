"""Video files and side-by-side frames."""

import numpy as np
import pytest

from usf_graph.videos import split_frame


def test_split_frame_cuts_side_by_side_cameras_in_order():
    frame = np.arange(4 * 6 * 3).reshape(4, 6, 3)
    parts = split_frame(frame, 3, "rig.yaml")
    assert [p.shape for p in parts] == [(4, 2, 3)] * 3
    assert np.array_equal(np.concatenate(parts, 1), frame) and parts[1][0, 0, 0] == frame[0, 2, 0]
    with pytest.raises(ValueError, match="has one camera"):
        split_frame(frame, 1, "rig.yaml")
    with pytest.raises(ValueError, match="6 pixels wide, which does not cut into 4"):
        split_frame(frame, 4, "rig.yaml")


def _written_mp4(path, frames: int = 3, faststart: bool = False):
    """An MPEG-4 video of ``frames`` different 128x64 frames: OpenCV's (its moov box after the
    media data) or, with ``faststart``, FFmpeg's through PyAV with the moov box first."""
    import cv2

    rng = np.random.default_rng(0)
    pictures = [cv2.GaussianBlur(rng.integers(0, 256, (64, 128, 3)).astype(np.uint8), (9, 9), 3)
                for _ in range(frames)]
    if not faststart:
        w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10, (128, 64))
        for p in pictures:
            w.write(p)
        w.release()
        return
    av = pytest.importorskip("av")
    with av.open(str(path), "w", options={"movflags": "faststart"}) as out:
        s = out.add_stream("mpeg4", rate=10)
        s.width, s.height, s.pix_fmt = 128, 64, "yuv420p"
        for p in pictures:
            out.mux(s.encode(av.VideoFrame.from_ndarray(p, format="bgr24")))
        out.mux(s.encode(None))


def _two_track_mp4(path, faststart: bool = False):
    """An MPEG-4 video with two video tracks of three flat 64x64 frames each, written
    interleaved (so each track's media lies in several chunks) by FFmpeg through PyAV."""
    av = pytest.importorskip("av")
    with av.open(str(path), "w", options={"movflags": "faststart"} if faststart else {}) as out:
        streams = [out.add_stream("mpeg4", rate=10) for _ in range(2)]
        for s in streams:
            s.width, s.height, s.pix_fmt = 64, 64, "yuv420p"
        for k in range(3):
            for j, s in enumerate(streams):
                img = np.full((64, 64, 3), 60 * j + 20 * k, np.uint8)
                out.mux(s.encode(av.VideoFrame.from_ndarray(img, format="rgb24")))
        for s in streams:
            out.mux(s.encode(None))
    return path


def _spherical(path, track: int = 0) -> list:
    """What FFmpeg (through PyAV) reads of each frame of video ``track``'s spherical side
    data: the projection (0: equirectangular), or None where a frame has none; and the
    frames' pixels."""
    av = pytest.importorskip("av")
    found, pixels = [], []
    with av.open(str(path)) as c:
        for f in c.decode(video=track):
            sd = [d for d in f.side_data if d.type.name == "SPHERICAL"]
            found.append(int.from_bytes(bytes(sd[0])[:4], "little") if sd else None)
            pixels.append(f.to_ndarray(format="rgb24"))
    return found, pixels


@pytest.mark.parametrize("faststart", [False, True], ids=["moov-last", "moov-first"])
def test_mark_spherical_makes_ffmpeg_read_an_equirectangular_360_video(tmp_path, faststart):
    """FFmpeg, not our reader, finds the Spherical Video metadata on every frame, and the
    frames decode as before: also where the moov box precedes the media data, whose chunk
    offsets then move. Marking again replaces the mark."""
    from usf_graph.videos import SPHERICAL_UUID, mark_spherical

    path = tmp_path / "pano.mp4"
    _written_mp4(path, faststart=faststart)
    plain, before = _spherical(path)
    assert plain == [None] * 3
    mark_spherical(path)
    marked, after = _spherical(path)
    assert marked == [0] * 3  # AV_SPHERICAL_EQUIRECTANGULAR
    assert all(np.array_equal(a, b) for a, b in zip(before, after))
    size = path.stat().st_size
    mark_spherical(path, software="again")
    data = path.read_bytes()
    assert path.stat().st_size == size - 4 and data.count(SPHERICAL_UUID) == 1  # "again": 4 bytes shorter
    assert b"<GSpherical:StitchingSoftware>again<" in data
    assert _spherical(path)[0] == [0] * 3


def _as_co64(path) -> None:
    """The MP4 ``path`` (its moov box before the media data) with 64-bit chunk offsets: each
    ``stco`` written as a ``co64``, the offsets moved by what the moov box grew, as a
    recorder writing files past 4 GiB does."""
    from usf_graph.videos import _children, _moov, _rebuilt

    start, size, head, moov = _moov(path)
    assert start + size < path.stat().st_size  # the media data after the moov box

    def tables(box, h):
        if box[4:8] == b"stco":
            return [int.from_bytes(box[h + 4:h + 8], "big")]
        return [n for k, b, bh in _children(box, h, "test")
                if k in (b"trak", b"mdia", b"minf", b"stbl", b"stco") for n in tables(b, bh)]

    grown = 4 * sum(tables(moov, head))

    def wide(box, h):
        if box[4:8] == b"stco":
            n = int.from_bytes(box[h + 4:h + 8], "big")
            offs = [int.from_bytes(box[h + 8 + 4 * k:h + 12 + 4 * k], "big") for k in range(n)]
            body = box[h:h + 8] + b"".join((o + grown).to_bytes(8, "big") for o in offs)
            return (8 + len(body)).to_bytes(4, "big") + b"co64" + body
        if box[4:8] in (b"moov", b"trak", b"mdia", b"minf", b"stbl"):
            return _rebuilt(box, h, [(k, wide(b, bh), bh) for k, b, bh in _children(box, h, "test")])
        return box

    data = path.read_bytes()
    path.write_bytes(data[:start] + wide(moov, head) + data[start + size:])


def test_mark_spherical_moves_64_bit_chunk_offsets(tmp_path):
    """A long recording's MP4 has 64-bit chunk offsets (``co64``): with its moov box first,
    marking moves them with the media data, and FFmpeg decodes the same frames, marked."""
    from usf_graph.videos import mark_spherical

    path = tmp_path / "long.mp4"
    _written_mp4(path, faststart=True)
    before = _spherical(path)[1]
    _as_co64(path)
    data = path.read_bytes()
    assert b"co64" in data and b"stco" not in data
    assert all(np.array_equal(a, b) for a, b in zip(before, _spherical(path)[1]))  # still the video
    mark_spherical(path)
    marked, after = _spherical(path)
    assert marked == [0] * 3 and len(after) == 3
    assert all(np.array_equal(a, b) for a, b in zip(before, after))


def test_mark_spherical_moves_every_chunk_of_every_track(tmp_path):
    """Two interleaved video tracks, moov box first: each track's media lies in several
    chunks, and marking moves every chunk offset of both; each track decodes to its own
    frames, marked."""
    from usf_graph.videos import mark_spherical

    path = _two_track_mp4(tmp_path / "two.mp4", faststart=True)
    data = path.read_bytes()
    stco = data.index(b"stco")
    assert data.index(b"moov") < data.index(b"mdat") and int.from_bytes(data[stco + 8:stco + 12], "big") > 1
    before = [_spherical(path, t)[1] for t in (0, 1)]
    mark_spherical(path)
    for t in (0, 1):
        marked, after = _spherical(path, t)
        assert marked == [0] * 3 and len(after) == 3
        assert all(np.array_equal(a, b) for a, b in zip(before[t], after))
    assert not np.array_equal(before[0][0], before[1][0])


def test_mark_spherical_keeps_a_64_bit_moov_size_and_reads_past_a_last_empty_box(tmp_path):
    """A moov box with a 64-bit size (size 1, then 8 bytes) stays one when it grows; an
    8-byte box (an empty ``free``) that ends the file is a box. FFmpeg decodes the same
    frames, marked."""
    from usf_graph.videos import _moov, mark_spherical

    path = tmp_path / "large.mp4"
    _written_mp4(path)  # OpenCV's: the moov box last, so no media data moves
    before = _spherical(path)[1]
    start, size, _, moov = _moov(path)
    data = path.read_bytes()
    large = b"\0\0\0\x01moov" + (size + 8).to_bytes(8, "big") + moov[8:]
    path.write_bytes(data[:start] + large + data[start + size:] + b"\0\0\0\x08free")
    mark_spherical(path)
    start, size, head, moov = _moov(path)
    assert head == 16 and moov[:8] == b"\0\0\0\x01moov" and int.from_bytes(moov[8:16], "big") == size
    assert path.read_bytes().endswith(b"\0\0\0\x08free")
    marked, after = _spherical(path)
    assert marked == [0] * 3 and all(np.array_equal(a, b) for a, b in zip(before, after))


def test_mark_spherical_refuses_what_it_cannot_mark_and_keeps_the_file(tmp_path):
    from usf_graph.videos import mark_spherical, video_track_count

    path = tmp_path / "pano.mp4"
    _written_mp4(path)
    data = path.read_bytes()
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(data[:-100])  # the moov box at the end, cut short
    with pytest.raises(ValueError, match="runs past its parent"):
        mark_spherical(cut)
    assert cut.read_bytes() == data[:-100]  # nothing written
    (tmp_path / "x.avi").write_bytes(data)
    with pytest.raises(ValueError, match="write .mp4"):
        mark_spherical(tmp_path / "x.avi")
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"\0\0\0\x10free01234567")  # one box, no moov
    with pytest.raises(ValueError, match="0 moov boxes"):
        mark_spherical(junk)
    # moov first: the media data would move, and a 32-bit chunk offset past 4 GiB
    first = tmp_path / "first.mp4"
    _written_mp4(first, faststart=True)
    data = first.read_bytes()
    stco = data.index(b"stco")
    assert int.from_bytes(data[stco + 8:stco + 12], "big") == 1  # one chunk
    far = data[:stco + 12] + (2**32 - 4).to_bytes(4, "big") + data[stco + 16:]
    first.write_bytes(far)
    with pytest.raises(ValueError, match="would move past 4 GiB"):
        mark_spherical(first)
    assert first.read_bytes() == far
    assert video_track_count(tmp_path / "x.avi") == 0  # no MP4: no tracks read


def _with_v2_boxes(path, stereo_mode: int, projection: bytes) -> None:
    """Spherical Video V2 boxes put into the video's sample entry: ``st3d`` (a stereo mode)
    and ``sv3d`` (header, then ``proj``: ``prhd`` and ``projection``'s box), the sizes of
    every box above them grown (the moov box is OpenCV's, after the media data)."""
    from usf_graph.videos import _children, _moov, _rebuilt

    def full(kind: bytes, payload: bytes) -> bytes:
        return (12 + len(payload)).to_bytes(4, "big") + kind + b"\0\0\0\0" + payload

    def plain(kind: bytes, payload: bytes) -> bytes:
        return (8 + len(payload)).to_bytes(4, "big") + kind + payload

    st3d = full(b"st3d", bytes([stereo_mode]))
    shape = bytes(8) if projection == b"cbmp" else bytes(16)  # layout, padding / bounds
    sv3d = plain(b"sv3d", full(b"svhd", b"test\0") + plain(b"proj", full(b"prhd", bytes(12)) + full(projection, shape)))
    start, size, head, moov = _moov(path)

    def grown(box, h, route):
        if box[4:8] == b"stsd":  # its version, flags and entry count, then the sample entries
            (kind, entry, eh), *rest = _children(box, h + 8, "test")
            return _rebuilt(box, h + 8, [(kind, grown(entry, eh, ()), eh), *rest])
        if not route:  # the sample entry: its fields, its children, then the V2 boxes
            return _rebuilt(box, h + 78, [*_children(box, h + 78, "test"), (b"st3d", st3d, 8),
                                          (b"sv3d", sv3d, 8)])
        return _rebuilt(box, h, [(k, grown(b, bh, route[1:]) if k == route[0] else b, bh)
                                 for k, b, bh in _children(box, h, "test")])

    new = grown(moov, head, (b"trak", b"mdia", b"minf", b"stbl", b"stsd"))
    data = path.read_bytes()
    path.write_bytes(data[:start] + new + data[start + size:])


def _side_data(path) -> dict:
    """What FFmpeg (through PyAV) attaches to the first decoded frame: the first int of its
    spherical (projection) and stereo 3D (type) side data, by name."""
    av = pytest.importorskip("av")
    with av.open(str(path)) as c:
        frame = next(c.decode(video=0))
        return {d.type.name: int.from_bytes(bytes(d)[:4], "little") for d in frame.side_data
                if d.type.name in ("SPHERICAL", "STEREO3D")}


def test_spherical_metadata_reads_v1_and_v2_as_ffmpeg_does(tmp_path):
    """V1 (our mark, with a stereo mode) and V2 boxes (written here): FFmpeg's reading of
    each file says the same as ours; a stereo or cube map video is refused as one
    equirectangular panorama, a plain or mono one passes."""
    from usf_graph.videos import check_panorama_video, mark_spherical, spherical_metadata

    plain = tmp_path / "plain.mp4"
    _written_mp4(plain)
    assert spherical_metadata(plain) is None and _side_data(plain) == {}
    check_panorama_video(plain)
    v1 = tmp_path / "v1.mp4"
    v1.write_bytes(plain.read_bytes())
    mark_spherical(v1, stereo="top-bottom")
    assert spherical_metadata(v1) == {"projection": "equirectangular", "stereo": "top-bottom", "version": 1}
    assert _side_data(v1) == {"SPHERICAL": 0, "STEREO3D": 2}  # equirectangular; AV_STEREO3D_TOPBOTTOM
    with pytest.raises(ValueError, match=r"stereo \(top-bottom\).*one panorama per eye"):
        check_panorama_video(v1)
    mark_spherical(v1)  # mono again
    check_panorama_video(v1)
    for mode, proj, want, ffmpeg in ((0, b"equi", ("equirectangular", "mono"), {"SPHERICAL": 0, "STEREO3D": 0}),
                                     (2, b"equi", ("equirectangular", "left-right"), {"SPHERICAL": 0, "STEREO3D": 1}),
                                     (0, b"cbmp", ("cubemap", "mono"), {"SPHERICAL": 1, "STEREO3D": 0})):
        v2 = tmp_path / f"v2_{mode}_{proj.decode()}.mp4"
        v2.write_bytes(plain.read_bytes())
        _with_v2_boxes(v2, mode, proj)
        assert _side_data(v2) == ffmpeg, (mode, proj)
        assert spherical_metadata(v2) == {"projection": want[0], "stereo": want[1], "version": 2}
        if want == ("equirectangular", "mono"):
            check_panorama_video(v2)
        else:
            with pytest.raises(ValueError, match="stereo" if mode else "projection cubemap.*cubemap:c3x2"):
                check_panorama_video(v2)
    # modes and projections the RFC does not name are said as they are
    v2.write_bytes(plain.read_bytes())
    _with_v2_boxes(v2, 7, b"abcd")
    assert spherical_metadata(v2) == {"projection": "unknown", "stereo": "mode 7", "version": 2}


def test_eye_image_is_the_half_its_layout_names():
    from usf_graph.videos import eye_image

    left, right = np.zeros((4, 6, 3)), np.ones((4, 6, 3))
    for layout, frame, want in (("top-bottom", np.concatenate([left, right], 0), (left, right)),
                                ("left-right", np.concatenate([left, right], 1), (left, right)),
                                ("right-left", np.concatenate([right, left], 1), (left, right))):
        assert np.array_equal(eye_image(frame, layout, "left"), want[0]), layout
        assert np.array_equal(eye_image(frame, layout, "right"), want[1]), layout
    for args, why in (((np.zeros((5, 6)), "top-bottom", "left"), "even height, got 5"),
                      ((np.zeros((4, 7)), "left-right", "right"), "even width, got 7"),
                      ((np.zeros((4, 6)), "stereo-custom", "left"), "cannot be cut"),
                      ((np.zeros((4, 6)), "top-bottom", "both"), "'left' or 'right'")):
        with pytest.raises(ValueError, match=why):
            eye_image(*args)


def test_frames_of_one_eye_are_where_ffmpeg_reads_that_eye(tmp_path):
    """A stereo 360 video's ``frames(eye=)``: the half its metadata names, V1 and V2, as
    FFmpeg reads the layout (its stereo 3D side data: top-bottom or side by side, and not
    inverted, i.e. the left eye on top or on the left); a video without a stereo layout
    is refused."""
    from usf_graph.videos import check_panorama_video, frames, mark_spherical

    plain = tmp_path / "plain.mp4"
    _written_mp4(plain)  # 128x64 frames
    whole = [f for _, f in frames(plain)]
    av = pytest.importorskip("av")
    v1 = tmp_path / "v1.mp4"
    v1.write_bytes(plain.read_bytes())
    mark_spherical(v1, stereo="top-bottom")
    cases = [(v1, 2, (slice(0, 32), slice(None)), (slice(32, 64), slice(None)))]
    for mode, ffmpeg, left, right in ((2, 1, (slice(None), slice(0, 64)), (slice(None), slice(64, 128))),
                                      (4, None, (slice(None), slice(64, 128)), (slice(None), slice(0, 64)))):
        v2 = tmp_path / f"v2_{mode}.mp4"
        v2.write_bytes(plain.read_bytes())
        _with_v2_boxes(v2, mode, b"equi")
        cases.append((v2, ffmpeg, left, right))
    for path, ffmpeg, left, right in cases:
        check_panorama_video(path, "left")
        for eye, where in (("left", left), ("right", right)):
            got = [f for _, f in frames(path, eye=eye)]
            assert len(got) == 3 and all(np.array_equal(g, w[where]) for g, w in zip(got, whole)), (path, eye)
        if ffmpeg is not None:  # FFmpeg reads no right-left mode: only ours
            with av.open(str(path)) as c:
                sd = {d.type.name: bytes(d) for d in next(c.decode(video=0)).side_data}
            assert int.from_bytes(sd["STEREO3D"][:4], "little") == ffmpeg  # its type
            assert int.from_bytes(sd["STEREO3D"][4:8], "little") & 1 == 0  # AV_STEREO3D_FLAG_INVERT
    for path, why in ((plain, "has no 360 video metadata: picking an eye"),
                      (v1, "says mono: picking an eye")):
        if path == v1:
            mark_spherical(v1)
        with pytest.raises(ValueError, match=why):
            next(frames(path, eye="left"))
        with pytest.raises(ValueError, match=why):
            check_panorama_video(path, "left")
    custom = tmp_path / "custom.mp4"
    custom.write_bytes(plain.read_bytes())
    _with_v2_boxes(custom, 3, b"equi")
    with pytest.raises(ValueError, match="stereo layout stereo-custom, which cannot be cut"):
        next(frames(custom, eye="right"))


def test_an_insta360_insv_is_read_as_the_mp4_it_is(tmp_path):
    from usf_graph.videos import frames, is_video, mark_spherical, spherical_metadata

    mp4, insv = tmp_path / "a.mp4", tmp_path / "VID_20260101_000000_00_001.insv"
    _written_mp4(mp4)
    insv.write_bytes(mp4.read_bytes())
    assert is_video(insv)
    got, want = [f for _, f in frames(insv)], [f for _, f in frames(mp4)]
    assert len(got) == 3 and all(np.array_equal(g, w) for g, w in zip(got, want))
    mark_spherical(insv, stereo="left-right")
    assert spherical_metadata(insv) == {"projection": "equirectangular", "stereo": "left-right", "version": 1}
    # the trailer Insta360 writes after the boxes (records, then the footer: 32 reserved
    # bytes, the trailer's size from its start, a version, the magic text) is no box
    records = bytes(range(256)) * 3
    footer = bytes(32) + (len(records) + 72).to_bytes(4, "little") + (3).to_bytes(4, "little")
    insv.write_bytes(insv.read_bytes() + records + footer + b"8db42d694ccc418790edff439fe026bf")
    assert spherical_metadata(insv)["stereo"] == "left-right"
    mark_spherical(insv)  # mono again; the trailer kept, as it was, at the end
    assert spherical_metadata(insv)["stereo"] == "mono"
    assert insv.read_bytes().endswith(records + footer + b"8db42d694ccc418790edff439fe026bf")
    assert all(np.array_equal(g, w) for g, w in zip(_spherical(insv)[1], _spherical(mp4)[1]))


def test_a_second_video_track_is_said_not_dropped(tmp_path):
    """An MP4 with a video track per lens (as some Insta360 files): OpenCV decodes the
    first, and reading it warns that there are more, with how to copy one out."""
    import warnings

    from usf_graph.videos import frames, video_track_count

    path = _two_track_mp4(tmp_path / "two.mp4")
    assert video_track_count(path) == 2
    with pytest.warns(UserWarning, match=r"holds 2 video tracks.*-map 0:v:1") as caught:
        got = list(frames(path))
    assert len(got) == 3 and caught[0].filename == __file__  # the reader's line, not ours
    single = tmp_path / "one.mp4"
    _written_mp4(single)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert video_track_count(single) == 1 and len(list(frames(single))) == 3
