"""VideoFrames: a video's frames lifted once (one camera, or a 360 camera's side-by-side
fisheyes onto one sphere), their index and time, the processed file."""

import warnings

import cv2
import numpy as np
import pytest
import torch

from tests.frontend.test_rig import scene
from tests.helpers import FIXTURES, decode_video
from usf_graph import cameras
from usf_graph.datasets import VideoFrames
from usf_graph.frontend import RigFrontend, SphericalFrontend, render


def write_video(path, frames, fps=5):
    h, w = frames[0].shape[:2]
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    for f in frames:
        out.write(np.ascontiguousarray(f[..., ::-1]))
    out.release()


@pytest.fixture(scope="module")
def world():
    """A smooth world turning 30 pixels a frame, as a 256x128 panorama."""
    pano = cameras.Equirectangular(256, 128)
    img = (255 * scene(pano.lens_normal_map()[0])).round().astype(np.uint8)
    return pano, [np.roll(img, 30 * k, axis=1) for k in range(4)]


def test_one_cameras_frames_are_lifted_once_with_their_time(tmp_path, world):
    pano, frames = world
    write_video(tmp_path / "walk.avi", frames)
    ds = VideoFrames(tmp_path / "data", tmp_path / "walk.avi", pano, grid="icosahedral:3", progress=False)
    assert len(ds) == 4 and "VideoFrames(4, video=walk.avi" in repr(ds)
    fe = SphericalFrontend(pano, ds.grid)
    for i, rgb in enumerate(decode_video(tmp_path / "walk.avi")[0]):
        d = ds[i]
        torch.testing.assert_close(d.x, fe.lift(rgb.astype(np.float32) / 255).to(torch.float16).float())
        assert d.frame.item() == i and d.stamp_ns.item() == i * 200_000_000  # 5 frames a second
        assert torch.equal(d.mask, fe.mask) and d.x.shape == (642, 3)
    assert (ds[0].x - ds[1].x).abs().mean() > 0.05  # the frames differ
    files = sorted((tmp_path / "data" / "processed").glob("video_*.pt"))
    before = files[0].stat().st_mtime_ns
    again = VideoFrames(tmp_path / "data", tmp_path / "walk.avi", pano, grid="icosahedral:3", progress=False)
    assert files[0].stat().st_mtime_ns == before and torch.equal(again.x, ds.x)  # not lifted again
    half = VideoFrames(tmp_path / "data", tmp_path / "walk.avi", pano, grid="icosahedral:3", every=3,
                       progress=False)
    assert half.frame.tolist() == [0, 3] and torch.equal(half.x[1], ds.x[3])
    cut = VideoFrames(tmp_path / "data", tmp_path / "walk.avi", pano, grid="icosahedral:3", every=3,
                      fov_deg=120, progress=False)
    assert cut.cameras["camera"].key() == pano.with_fov(120).key()
    assert torch.equal(cut[0].mask, SphericalFrontend(pano.with_fov(120), ds.grid).mask)
    assert 0 < cut[0].mask.sum() < 0.5 * len(cut[0].mask)
    files[0].write_bytes(b"not a tensor file")  # a corrupt processed file is made again
    with pytest.warns(UserWarning, match="unreadable"):
        fixed = VideoFrames(tmp_path / "data", tmp_path / "walk.avi", pano, grid="icosahedral:3", progress=False)
    assert torch.equal(fixed.x, ds.x)


def test_a_video_without_a_frame_rate_has_no_times(tmp_path, world, monkeypatch):
    import usf_graph.videos

    pano, frames = world
    write_video(tmp_path / "walk.avi", frames[:2])
    monkeypatch.setattr(usf_graph.videos, "info", lambda path: (0.0, 0))  # a header without one
    with pytest.warns(UserWarning, match="no frame rate"):
        ds = VideoFrames(tmp_path / "data", tmp_path / "walk.avi", pano, grid="icosahedral:2", progress=False)
    assert ds.stamp_ns.tolist() == [-1, -1] and ds.frame.tolist() == [0, 1]
    monkeypatch.undo()
    write_video(tmp_path / "lapse.avi", frames[:2], fps=0.5)  # a time-lapse: under a frame a second
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds = VideoFrames(tmp_path / "data", tmp_path / "lapse.avi", pano, grid="icosahedral:2", progress=False)
    assert ds.stamp_ns.tolist() == [0, 2 * 10**9]


def test_a_dual_fisheye_video_lifts_onto_one_sphere(tmp_path, world):
    """Each frame holds a Kalibr rig's two fisheyes side by side; split, they are lifted as
    RigFrontend lifts the two images, and the whole sphere is seen."""
    pano, frames = world
    rig = {n: c.with_fov(190) for n, c in cameras.load_rig(FIXTURES / "kalibr_rig.yaml").items()}
    write_video(tmp_path / "dual.avi", [np.concatenate([render(f, pano, c) for c in rig.values()], 1)
                                        for f in frames[:2]])
    ds = VideoFrames(tmp_path / "data", tmp_path / "dual.avi", FIXTURES / "kalibr_rig.yaml",
                     grid="icosahedral:3", split=True, fov_deg=190, progress=False)
    assert len(ds) == 2 and ds[0].mask.all() and "rig=[cam0, cam1]" in repr(ds)
    assert [c.key() for c in ds.cameras.values()] == [c.key() for c in rig.values()]  # fov_deg too
    fe = RigFrontend(rig, ds.grid)
    for d, rgb in zip(ds, decode_video(tmp_path / "dual.avi")[0]):
        want = fe.lift(np.split(rgb.astype(np.float32) / 255, 2, axis=1))
        torch.testing.assert_close(d.x, want.to(torch.float16).float())
    truth = torch.as_tensor(scene(ds.grid.pos.numpy()), dtype=torch.float32)
    assert (ds[0].x - truth).abs().mean() < 0.03  # the world, seen whole (Motion JPEG both ways)


def test_video_frames_refuses_what_it_cannot_read(tmp_path, world):
    pano, frames = world
    write_video(tmp_path / "walk.avi", frames[:1])
    for kwargs, err, match in (
            ({"video": tmp_path / "none.mp4"}, FileNotFoundError, "does not exist"),
            ({"every": 0}, ValueError, "positive whole number"),
            ({"camera": {"a": pano, "b": pano}}, ValueError, "split=True"),
            ({"camera": cameras.Equirectangular(128, 64)}, ValueError, "the camera expects")):
        args = {"root": tmp_path / "data", "video": tmp_path / "walk.avi", "camera": pano,
                "grid": "icosahedral:2", "progress": False, **kwargs}
        with pytest.raises(err, match=match):
            VideoFrames(**args)
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(ValueError, match="not named as a video"):
        VideoFrames(tmp_path / "data", tmp_path / "notes.txt", pano, progress=False)
    (tmp_path / "broken.mp4").write_bytes(b"not a video")
    with pytest.raises(ValueError, match="cannot read video"):
        VideoFrames(tmp_path / "data", tmp_path / "broken.mp4", pano, grid="icosahedral:2", progress=False)


def test_a_stereo_360_video_is_lifted_one_eye_at_a_time(tmp_path, world):
    """Its 360 metadata says each frame holds one panorama per eye (side by side): refused
    as one panorama; with ``eye``, that eye's panorama is lifted, and a mono video's eye
    is refused."""
    from usf_graph.videos import mark_spherical

    pano, frames = world
    w = cv2.VideoWriter(str(tmp_path / "vr.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 5, (512, 128))
    for f in frames[:2]:  # the right eye's panorama turned by 64 pixels
        w.write(np.ascontiguousarray(np.concatenate([f, np.roll(f, 64, axis=1)], 1)[..., ::-1]))
    w.release()
    mark_spherical(tmp_path / "vr.mp4", stereo="left-right")
    with pytest.raises(ValueError, match=r"stereo \(left-right\).*--eye left or --eye right"):
        VideoFrames(tmp_path / "data", tmp_path / "vr.mp4", pano, grid="icosahedral:2", progress=False)
    eyes = {e: VideoFrames(tmp_path / "data", tmp_path / "vr.mp4", pano, grid="icosahedral:3",
                           eye=e, progress=False) for e in ("left", "right")}
    fe = SphericalFrontend(pano, eyes["left"].grid)
    for i, rgb in enumerate(decode_video(tmp_path / "vr.mp4")[0]):
        for e, half in (("left", rgb[:, :256]), ("right", rgb[:, 256:])):
            torch.testing.assert_close(eyes[e][i].x, fe.lift(half.astype(np.float32) / 255).to(torch.float16).float())
    assert (eyes["left"].x - eyes["right"].x).abs().mean() > 0.05  # the eyes' panoramas differ
    mark_spherical(tmp_path / "vr.mp4")  # mono: lifted whole, and no eye to pick
    assert len(VideoFrames(tmp_path / "data", tmp_path / "vr.mp4", cameras.Equirectangular(512, 128),
                           grid="icosahedral:2", progress=False)) == 2
    with pytest.raises(ValueError, match="says mono: picking an eye"):
        VideoFrames(tmp_path / "data", tmp_path / "vr.mp4", pano, grid="icosahedral:2", eye="left",
                    progress=False)
