import argparse
import functools
import importlib
import inspect
import math
import re

import cv2
import numpy as np
import pytest
import torch

import usf_graph
from tests.helpers import FIXTURES, decode_video, tiny_seg_checkpoint
from usf_graph import SphericalFrontend, SphericalImage, cameras, grids
from usf_graph.cli import build_parser, main
from usf_graph.frontend import RigFrontend, load_lifted, read_lifted


def test_lift_cli_writes_sample_and_preview(tmp_path, capsys):
    cam = cameras.KannalaBrandt(60.0, 60.0, 79.5, 59.5, 160, 120, k=(0.01, 0, 0, 0))
    cam.save(tmp_path / "cam.yaml")
    rng = np.random.default_rng(0)
    img = (rng.random((120, 160, 3)) * 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "img.png"), img[..., ::-1])  # cv2 writes BGR
    rc = main(["lift", str(tmp_path / "img.png"), "--camera", str(tmp_path / "cam.yaml"),
               "--grid", "icosahedral:4", "--out", str(tmp_path / "s.pt"),
               "--preview", str(tmp_path / "s.png")])
    assert rc == 0
    out = capsys.readouterr()
    assert "points visible" in out.out and "building lift table" in out.err
    fe = SphericalFrontend(cameras.load(tmp_path / "cam.yaml"), grids.icosahedral(4))
    ref = fe(img)
    back = load_lifted(tmp_path / "s.pt")  # the documented way back
    assert isinstance(back, SphericalImage) and torch.equal(back.x, ref.x)
    for k in ("mask", "pos", "area", "edge_index", "edge_attr"):
        assert torch.equal(back[k], ref[k]), k
    assert back.mask.sum() == (ref.x.abs().sum(1) > 0).sum() > 100
    # the file holds the signal, the mask and the spec, not the graph
    blob = read_lifted(tmp_path / "s.pt")
    assert set(blob) >= {"x", "mask", "grid", "radius", "interpolation", "cameras"}
    assert "edge_index" not in blob and blob["grid"] == "icosahedral:4"
    assert cameras.from_doc(blob["cameras"]["cam0"]).key() == fe.camera.key()
    assert (tmp_path / "s.pt").stat().st_size < ref.x.numel() * 4 + 2562 + 8_000
    assert (tmp_path / "s.png").stat().st_size > 10_000
    # a preview matplotlib cannot write stops the command before it writes anything
    assert main(["lift", str(tmp_path / "img.png"), "--camera", str(tmp_path / "cam.yaml"),
                 "--grid", "icosahedral:4", "--out", str(tmp_path / "t.pt"),
                 "--preview", str(tmp_path / "t.xyz")]) == 2
    assert "Format 'xyz' is not supported" in capsys.readouterr().err
    assert not (tmp_path / "t.pt").exists() and not list(tmp_path.glob(".t.*"))
    torch.save({"format": "usf_graph.lifted", "version": 99}, tmp_path / "old.pt")
    with pytest.raises(ValueError, match="version 99"):
        load_lifted(tmp_path / "old.pt")
    (tmp_path / "cut.pt").write_bytes((tmp_path / "s.pt").read_bytes()[:500])
    with pytest.raises(ValueError, match="not a readable lifted file"):
        load_lifted(tmp_path / "cut.pt")


def test_lift_cli_keeps_rgba_order_panoramas_fov_and_masks(tmp_path, capsys):
    rgba = np.zeros((32, 64, 4), np.uint8)
    rgba[..., 0], rgba[..., 3] = 200, 255  # red, opaque
    cv2.imwrite(str(tmp_path / "pano.png"), cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
    assert main(["lift", str(tmp_path / "pano.png"), "--camera", "equirectangular",
                 "--grid", "icosahedral:2", "--out", str(tmp_path / "p.pt")]) == 0
    x = load_lifted(tmp_path / "p.pt").x
    assert (x[:, 0] == 200).all() and (x[:, 2] == 0).all() and (x[:, 3] == 255).all()
    # --fov and --image-mask reach the camera; the lifted file records them
    kb = cameras.KannalaBrandt(40, 40, 63.5, 63.5, 128, 128)
    kb.save(tmp_path / "kb.yaml")
    cv2.imwrite(str(tmp_path / "img.png"), np.full((128, 128), 90, np.uint8))
    mask = np.full((128, 128), 255, np.uint8)
    mask[:, :64] = 0
    cv2.imwrite(str(tmp_path / "m.png"), mask)
    args = ["lift", str(tmp_path / "img.png"), "--camera", str(tmp_path / "kb.yaml"),
            "--grid", "icosahedral:3", "--out", str(tmp_path / "k.pt")]
    assert main(args) == 0
    full = load_lifted(tmp_path / "k.pt").mask.sum()
    assert main(args + ["--fov", "180"]) == 0
    half = load_lifted(tmp_path / "k.pt")
    assert read_lifted(tmp_path / "k.pt")["cameras"]["cam0"]["fov_deg"] == 180
    assert half.mask.sum() < full and (half.pos[half.mask, 0] >= -1e-9).all()
    assert main(args + ["--fov", "180", "--image-mask", str(tmp_path / "m.png")]) == 0
    left = load_lifted(tmp_path / "k.pt")
    assert 0 < left.mask.sum() < 0.6 * half.mask.sum()
    assert (left.pos[left.mask, 1] <= 1e-9).all()  # only the image's right half: y <= 0
    capsys.readouterr()
    assert main(args + ["--key", "cam1"]) == 2
    assert "--key" in capsys.readouterr().err


def test_lift_cli_lifts_a_rig_onto_one_sphere(tmp_path, capsys):
    rig = FIXTURES / "kalibr_rig.yaml"
    for i, v in enumerate((60, 180)):
        cv2.imwrite(str(tmp_path / f"cam{i}.png"), np.full((400, 400), v, np.uint8))
    assert main(["lift", str(tmp_path / "cam0.png"), str(tmp_path / "cam1.png"), "--camera",
                 str(rig), "--grid", "icosahedral:3", "--fov", "190",
                 "--out", str(tmp_path / "r.pt")]) == 0
    img = load_lifted(tmp_path / "r.pt")
    assert img.mask.all()
    front, back = img.pos[:, 0] > 0.1, img.pos[:, 0] < -0.1
    assert (img.x[front] == 60).all() and (img.x[back] == 180).all()
    assert set(read_lifted(tmp_path / "r.pt")["cameras"]) == {"cam0", "cam1"}
    capsys.readouterr()
    assert main(["lift", str(tmp_path / "cam0.png"), "--camera", str(rig), "--grid",
                 "icosahedral:2"]) == 0
    assert main(["lift", *(str(tmp_path / f"cam{i}.png") for i in (0, 1, 0)), "--camera",
                 str(rig), "--grid", "icosahedral:2"]) == 2
    assert "2 cameras" in capsys.readouterr().err
    # stitched at 1 m: the cameras 0.1 m apart look from their own centres
    ramp = [np.tile(np.arange(0, 400, dtype=np.uint8)[None] // 2, (400, 1)) + 40 * i for i in (0, 1)]
    for i in (0, 1):
        cv2.imwrite(str(tmp_path / f"ramp{i}.png"), ramp[i])
    assert main(["lift", str(tmp_path / "ramp0.png"), str(tmp_path / "ramp1.png"), "--camera",
                 str(rig), "--grid", "icosahedral:3", "--fov", "190", "--distance", "1",
                 "--out", str(tmp_path / "d.pt")]) == 0
    cams = {n: c.with_fov(190) for n, c in cameras.load_rig(rig).items()}
    want = RigFrontend(cams, grids.icosahedral(3), distance=1.0).lift([r[..., None] for r in ramp])
    got = load_lifted(tmp_path / "d.pt")
    torch.testing.assert_close(got.x, want.to(got.x.dtype))
    at_infinity = RigFrontend(cams, grids.icosahedral(3)).lift([r[..., None] for r in ramp])
    assert (got.x - at_infinity.to(got.x.dtype)).abs().max() > 2.5  # 6 px of parallax, 3 grey levels
    docs = read_lifted(tmp_path / "d.pt")["cameras"]
    assert docs["cam1"]["distance"] == 1.0 and docs["cam1"]["position"] == [-0.05, 0.0, 0.0]
    for i in (0, 1):  # the frames at half size: each camera scaled to its image
        cv2.imwrite(str(tmp_path / f"half{i}.png"), cv2.resize(ramp[i], (200, 200),
                                                               interpolation=cv2.INTER_AREA))
    assert main(["lift", str(tmp_path / "half0.png"), str(tmp_path / "half1.png"), "--camera",
                 str(rig), "--grid", "icosahedral:3", "--fov", "190", "--out",
                 str(tmp_path / "h.pt")]) == 0
    assert capsys.readouterr().out.count("scaling the calibration by 0.5") == 2
    halves = [cv2.imread(str(tmp_path / f"half{i}.png"), cv2.IMREAD_UNCHANGED)[..., None]
              for i in (0, 1)]
    small = {n: c.resized(200, 200) for n, c in cams.items()}
    torch.testing.assert_close(load_lifted(tmp_path / "h.pt").x,
                               RigFrontend(small, grids.icosahedral(3)).lift(halves).float())
    assert main(["lift", str(tmp_path / "cam0.png"), "--camera", str(rig), "--distance", "1"]) == 2
    assert "--distance stitches a rig's cameras" in capsys.readouterr().err
    assert main(["lift", str(tmp_path / "cam0.png"), str(tmp_path / "cam1.png"), "--camera",
                 str(rig), "--distance", "0.03"]) == 2
    assert "does not reach past the rig: a camera is 0.05" in capsys.readouterr().err


def test_a_cropped_photo_sphere_is_read_as_its_crop(tmp_path, capsys):
    """A phone's panorama that stops short of the poles: ``--camera equirectangular`` reads
    its Photo Sphere XMP (written here by Pillow) and puts each pixel where it belongs in
    the full sphere, with a note; read as a whole sphere it would be stretched."""
    from PIL import Image

    from tests.test_fileio import _photo_sphere_xmp
    from usf_graph.viz import labelled_panorama

    full = cv2.GaussianBlur((255 * labelled_panorama(720, 360)).round().astype(np.uint8), (0, 0), 2)
    crop = full[60:240, 90:450]
    gpano = {"ProjectionType": "equirectangular", "FullPanoWidthPixels": 720,
             "FullPanoHeightPixels": 360, "CroppedAreaImageWidthPixels": 360,
             "CroppedAreaImageHeightPixels": 180, "CroppedAreaLeftPixels": 90,
             "CroppedAreaTopPixels": 60}
    Image.fromarray(crop).save(tmp_path / "crop.jpg", quality=95, xmp=_photo_sphere_xmp(gpano, True))
    Image.fromarray(crop).save(tmp_path / "plain.jpg", quality=95)
    errors = []
    for name in ("crop.jpg", "plain.jpg"):
        assert main(["render", str(tmp_path / name), "--camera", "equirectangular", "--to",
                     "equirectangular:720x360", "--out", str(tmp_path / "out.png")]) == 0
        out = cv2.imread(str(tmp_path / "out.png"))[..., ::-1].astype(float)
        errors.append(np.abs(out[70:230, 100:440] - full[70:230, 100:440]).mean())
        if name == "crop.jpg":
            assert "a Photo Sphere cropped to latitudes -30.0 to 60.0 and longitudes -45.0 to 135.0" \
                in capsys.readouterr().out
            assert out[:50].max() == 0 and out[250:].max() == 0  # nothing beyond the crop
    assert errors[0] < 3 and errors[1] > 5 * errors[0]  # JPEG; the whole-sphere reading stretched


def test_render_into_and_out_of_cube_maps(tmp_path, capsys):
    """``--to cubemap[:SIZE][:LAYOUT]`` (a face a quarter of the source's width by default)
    is the frontend's render into a Cubemap; ``--camera cubemap`` reads the layout from the
    image's shape; a cube map is a whole sphere but no equirectangular 360 photo."""
    from usf_graph.frontend import render
    from usf_graph.viz import labelled_panorama

    pano = (255 * labelled_panorama(256, 128)).round().astype(np.uint8)
    cv2.imwrite(str(tmp_path / "pano.png"), pano[..., ::-1])
    eq = cameras.Equirectangular(256, 128)
    for to, cube in (("cubemap", cameras.Cubemap(64)), ("cubemap:40:dice", cameras.Cubemap(40, "dice"))):
        assert main(["render", str(tmp_path / "pano.png"), "--camera", "equirectangular",
                     "--to", to, "--out", str(tmp_path / "cube.png")]) == 0
        assert f"Cubemap {cube.width}x{cube.height}" in capsys.readouterr().out
        got = cv2.imread(str(tmp_path / "cube.png"))[..., ::-1]
        assert np.array_equal(got, render(pano, eq, cube))
    assert main(["render", str(tmp_path / "pano.png"), "--camera", "equirectangular",
                 "--to", "cubemap", "--out", str(tmp_path / "cube.jpg")]) == 0
    assert b"GPano" not in (tmp_path / "cube.jpg").read_bytes()  # no equirectangular 360 photo
    cv2.imwrite(str(tmp_path / "dice.png"), render(pano, eq, cameras.Cubemap(40, "dice"))[..., ::-1])
    # YouTube's equi-angular cube map, its size from the image (3:2, as FFmpeg's c3x2 cube
    # map: a plain "cubemap" asks which)
    assert main(["render", str(tmp_path / "pano.png"), "--camera", "equirectangular", "--to", "eac",
                 "--out", str(tmp_path / "eac.png")]) == 0
    eac = cv2.imread(str(tmp_path / "eac.png"))[..., ::-1]
    assert eac.shape[:2] == (2 * (pano.shape[1] // 4), 3 * (pano.shape[1] // 4))
    assert main(["render", str(tmp_path / "eac.png"), "--camera", "eac", "--to",
                 "equirectangular:256x128", "--out", str(tmp_path / "back.png")]) == 0
    back = cv2.imread(str(tmp_path / "back.png"))[..., ::-1]
    cam = cameras.EquiAngularCubemap(eac.shape[1], eac.shape[0])
    assert np.abs(back.astype(float) - render(eac, cam, eq)).max() <= 1
    assert main(["render", str(tmp_path / "dice.png"), "--camera", "cubemap", "--to",
                 "equirectangular:256x128", "--out", str(tmp_path / "back.png")]) == 0
    back = cv2.imread(str(tmp_path / "back.png"))[..., ::-1]
    want = render(render(pano, eq, cameras.Cubemap(40, "dice")), cameras.Cubemap(40, "dice"), eq)
    assert np.abs(back.astype(float) - want).max() <= 1
    assert main(["camera", "cubemap:32:dice"]) == 0
    assert "100.00% of the sphere" in capsys.readouterr().out
    for spec, image, why in (("cubemap:big", "pano.png", "write cubemap[:SIZE][:LAYOUT]"),
                             ("cubemap:0:dice", "pano.png", "'cubemap:0:dice': write cubemap[:SIZE]"),
                             ("cubemap", "pano.png", "a cube map's is 6:1 (horizon, c6x1), 4:3 (dice)"),
                             ("cubemap:horizon", "dice.png", "give its layout and face size"),
                             ("cubemap", "eac.png", "3:2: name its kind, cubemap:c3x2")):
        assert main(["render", str(tmp_path / image), "--camera", spec, "--to", "equirectangular",
                     "--out", str(tmp_path / "x.png")]) == 2
        assert why in capsys.readouterr().err
    for argv, why in ((["cubemap:32", "--key", "cam0"], "a cube map has none"),
                      (["equirectangular:64x32", "--key", "cam0"], "a panorama has none"),
                      (["equirectangular"], "give the panorama's size: equirectangular:WIDTHxHEIGHT")):
        assert main(["camera", *argv]) == 2 and why in capsys.readouterr().err  # no image to size it


def test_render_and_camera_save_commands(tmp_path, capsys):
    pano = np.zeros((64, 128, 3), np.uint8)
    pano[:, 40:64] = (255, 0, 0)  # red, left of the centre column (64): longitude > 0
    cv2.imwrite(str(tmp_path / "pano.png"), pano[..., ::-1])
    assert main(["camera", "equirectangular:128x64", "--save", str(tmp_path / "pano.yaml")]) == 0
    assert isinstance(cameras.load(tmp_path / "pano.yaml"), cameras.Equirectangular)
    cameras.Pinhole(50, 50, 49.5, 49.5, 100, 100).save(tmp_path / "pin.yaml")
    assert main(["render", str(tmp_path / "pano.png"), "--camera", str(tmp_path / "pano.yaml"),
                 "--to", str(tmp_path / "pin.yaml"), "--out", str(tmp_path / "view.png")]) == 0
    view = cv2.imread(str(tmp_path / "view.png"))[..., ::-1]
    # the red band left of the panorama's centre is left of the pinhole's centre, in red
    assert view[50, 20, 0] > 200 and view[50, 20, 2] == 0 and view[50, 80].max() == 0
    # a target is taken at its own size (not fitted to the source image, even at the same
    # aspect); a panorama without a size gets the source's width at 2:1
    cameras.Pinhole(100, 100, 99.5, 99.5, 200, 200).save(tmp_path / "pin2.yaml")
    for to, shape in ((str(tmp_path / "pin2.yaml"), (200, 200, 3)), ("equirectangular", (50, 100, 3))):
        assert main(["render", str(tmp_path / "view.png"), "--camera", str(tmp_path / "pin.yaml"),
                     "--to", to, "--out", str(tmp_path / "again.png")]) == 0
        assert cv2.imread(str(tmp_path / "again.png")).shape == shape


def test_render_stitches_a_rigs_images(tmp_path, capsys):
    from tests.test_fileio import _gpano
    from usf_graph.frontend import render, render_rig
    from usf_graph.viz import labelled_panorama

    rig = {n: c.with_fov(190) for n, c in cameras.load_rig(FIXTURES / "kalibr_rig.yaml").items()}
    text = (255 * labelled_panorama(512, 256)).round().astype(np.uint8)
    paths = []
    for n, c in rig.items():
        paths.append(str(tmp_path / f"{n}.png"))
        cv2.imwrite(paths[-1], render(text, cameras.Equirectangular(512, 256), c)[..., ::-1])
    views = [cv2.imread(p)[..., ::-1] for p in paths]
    common = ["render", *paths, "--camera", str(FIXTURES / "kalibr_rig.yaml"), "--fov", "190"]
    assert main([*common, "--to", "equirectangular:512x256", "--blend", "feather",
                 "--out", str(tmp_path / "pano.png")]) == 0
    assert "rig of 2 (cam0, cam1)" in capsys.readouterr().out
    got = cv2.imread(str(tmp_path / "pano.png"))[..., ::-1]
    assert np.array_equal(got, render_rig(views, rig, cameras.Equirectangular(512, 256), blend="feather"))
    # --split: one frame with both fisheyes side by side (a dual-fisheye 360 camera's)
    cv2.imwrite(str(tmp_path / "dual.png"), np.concatenate([cv2.imread(p) for p in paths], 1))
    split = ["--camera", str(FIXTURES / "kalibr_rig.yaml"), "--fov", "190", "--split"]
    assert main(["render", str(tmp_path / "dual.png"), *split, "--to", "equirectangular:512x256",
                 "--blend", "feather", "--out", str(tmp_path / "pano2.png")]) == 0
    assert np.array_equal(cv2.imread(str(tmp_path / "pano2.png")), cv2.imread(str(tmp_path / "pano.png")))
    assert "holds no 360 photo metadata" in capsys.readouterr().out  # a .png
    # a whole panorama as a .jpg: a 360 photo, as Pillow reads its XMP
    assert main(["render", str(tmp_path / "dual.png"), *split, "--to", "equirectangular:512x256",
                 "--out", str(tmp_path / "pano.jpg")]) == 0
    assert "marked as a 360 photo" in capsys.readouterr().out
    assert _gpano(tmp_path / "pano.jpg")["FullPanoWidthPixels"] == "512"
    for name, argv in (("apart", [*paths, *split[:-1]]), ("dual", [str(tmp_path / "dual.png"), *split])):
        assert main(["lift", *argv, "--grid", "icosahedral:3", "--out", str(tmp_path / f"{name}.pt")]) == 0
    assert torch.equal(load_lifted(tmp_path / "apart.pt").x, load_lifted(tmp_path / "dual.pt").x)
    capsys.readouterr()
    cv2.imwrite(str(tmp_path / "odd.png"), np.zeros((400, 801, 3), np.uint8))
    for argv, why in (([*paths, *split], "give one"), ([str(tmp_path / "odd.png"), *split], "801 pixels wide")):
        assert main(["render", *argv, "--to", "equirectangular:64x32", "--out", str(tmp_path / "x.png")]) == 2
        assert why in capsys.readouterr().err
    assert main([*common, "--to", "equirectangular", "--out", str(tmp_path / "x.png")]) == 2
    assert "give the panorama's size" in capsys.readouterr().err
    assert main(["render", paths[0], "--camera", str(FIXTURES / "kalibr_rig.yaml"), "--to",
                 "equirectangular", "--distance", "2", "--out", str(tmp_path / "x.png")]) == 2
    assert "give the rig's images" in capsys.readouterr().err


def test_render_re_images_videos_frame_by_frame(tmp_path, capsys):
    """``render`` of a dual-fisheye video (both circles side by side in each frame) gives
    the stitched panorama video: each frame what ``render_rig`` gives the decoded frame,
    at the source's frame rate; one camera's video with ``--every`` and ``--fps``; mixed or
    misdirected inputs are refused."""
    from tests.frontend.test_rig import scene
    from tests.test_videos import _spherical
    from usf_graph.frontend import render, render_rig
    from usf_graph.videos import mark_spherical

    rig = {n: c.with_fov(190) for n, c in cameras.load_rig(FIXTURES / "kalibr_rig.yaml").items()}
    big = cameras.Equirectangular(512, 256)
    text = (255 * scene(big.lens_normal_map()[0])).round().astype(np.uint8)  # smooth: JPEG keeps it
    first = next(iter(rig.values()))
    writer = cv2.VideoWriter(str(tmp_path / "dual.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 5,
                             (2 * first.width, first.height))
    for k in range(3):  # the world turns 40 pixels a frame
        moved = np.roll(text, 40 * k, axis=1)
        writer.write(np.concatenate([render(moved, big, c) for c in rig.values()], 1)[..., ::-1].copy())
    writer.release()
    split = ["--camera", str(FIXTURES / "kalibr_rig.yaml"), "--fov", "190", "--split"]
    assert main(["render", str(tmp_path / "dual.avi"), *split, "--to", "equirectangular:256x128",
                 "--out", str(tmp_path / "pano.avi")]) == 0
    out = capsys.readouterr().out
    assert "wrote" in out and "holds no 360 video metadata" in out
    got, fps = decode_video(tmp_path / "pano.avi")
    frames, _ = decode_video(tmp_path / "dual.avi")
    assert len(got) == 3 and fps == 5
    pano = cameras.Equirectangular(256, 128)
    for g, f in zip(got, frames):
        want = render_rig(np.split(f, 2, axis=1), rig, pano)
        assert np.abs(g.astype(float) - want).mean() < 2  # Motion JPEG, both ways
    assert np.abs(got[0].astype(float) - got[1]).mean() > 10  # the frames differ
    # one camera, every second frame, another rate: frames 0 and 2
    cv2.imwrite(str(tmp_path / "cam0.png"), np.zeros((first.height, first.width, 3), np.uint8))
    assert main(["render", str(tmp_path / "pano.avi"), "--camera", "equirectangular",
                 "--to", "equirectangular:128x64", "--every", "2", "--fps", "7",
                 "--out", str(tmp_path / "small.mp4")]) == 0
    small, fps = decode_video(tmp_path / "small.mp4")
    assert len(small) == 2 and fps == 7 and small[0].shape == (64, 128, 3)
    assert "marked as a 360 video" in capsys.readouterr().out  # a whole panorama in an mp4
    assert _spherical(tmp_path / "small.mp4")[0] == [0, 0]  # as FFmpeg reads it
    # a stereo 360 video (one panorama per eye in each frame) is not read as one panorama
    mark_spherical(tmp_path / "small.mp4", stereo="top-bottom")
    for argv in (["render", str(tmp_path / "small.mp4"), "--camera", "equirectangular", "--to",
                  "equirectangular:64x32", "--out", str(tmp_path / "x.mp4")],
                 ["predict", "seg", str(tmp_path / "none.pt"), str(tmp_path / "small.mp4"),
                  "--camera", "equirectangular", "--out", str(tmp_path / "p")]):
        assert main(argv) == 2
        assert "stereo (top-bottom): each frame holds one panorama per eye" in capsys.readouterr().err
    for argv, why in (([str(tmp_path / "pano.avi"), str(tmp_path / "cam0.png")], "not both"),
                      ([str(tmp_path / "cam0.png"), "--every", "2"], "none was given"),
                      ([str(tmp_path / "pano.avi"), "--out", str(tmp_path / "x.png")], ".mp4 or .avi")):
        argv = argv if "--out" in argv else [*argv, "--out", str(tmp_path / "x.avi")]
        assert main(["render", *argv, "--camera", "equirectangular", "--to", "equirectangular:64x32"]) == 2
        assert why in capsys.readouterr().err


def test_render_reads_one_eye_of_a_stereo_360_video(tmp_path, capsys):
    """``render --eye``: of a top-bottom stereo 360 video, the eye's panorama re-imaged (the
    right eye's: the bottom half of each frame); an eye is refused on images and on a
    video whose metadata says mono, before a model loads."""
    from tests.frontend.test_rig import scene
    from usf_graph.videos import mark_spherical

    pano = cameras.Equirectangular(128, 64)
    img = (255 * scene(pano.lens_normal_map()[0])).round().astype(np.uint8)
    vr = tmp_path / "vr.mp4"
    w = cv2.VideoWriter(str(vr), cv2.VideoWriter_fourcc(*"mp4v"), 5, (128, 128))
    for k in range(2):  # the right eye's panorama turned by 32 pixels more
        eyes = np.concatenate([np.roll(img, 8 * k, axis=1), np.roll(img, 8 * k + 32, axis=1)], 0)
        w.write(np.ascontiguousarray(eyes[..., ::-1]))
    w.release()
    mark_spherical(vr, stereo="top-bottom")
    assert main(["render", str(vr), "--camera", "equirectangular", "--eye", "right", "--to",
                 "equirectangular:128x64", "--out", str(tmp_path / "right.mp4")]) == 0
    assert "Equirectangular 128x64" in capsys.readouterr().out
    got, source = decode_video(tmp_path / "right.mp4")[0], decode_video(vr)[0]
    assert len(got) == 2
    for g, f in zip(got, source):
        assert np.abs(g.astype(float) - f[64:]).mean() < 3  # the same panorama, MPEG-4 twice
        assert np.abs(g.astype(float) - f[:64]).mean() > 10  # not the left eye's
    mark_spherical(vr)  # mono
    cv2.imwrite(str(tmp_path / "pano.png"), img)
    for argv, why in ((["render", str(vr), "--to", "equirectangular:64x32", "--out", str(tmp_path / "x.mp4")],
                       "says mono: picking an eye (left)"),
                      (["render", str(tmp_path / "pano.png"), "--to", "equirectangular:64x32", "--out",
                        str(tmp_path / "x.png")], "--eye picks one eye of a stereo 360 video's frames"),
                      (["predict", "seg", str(tmp_path / "none.pt"), str(vr), "--out", str(tmp_path / "p")],
                       "says mono: picking an eye (left)")):
        assert main([*argv, "--camera", "equirectangular", "--eye", "left"]) == 2
        assert why in capsys.readouterr().err


def test_render_level_each_holds_a_tilting_cameras_horizon(tmp_path, capsys):
    """``render --level-each``: a panorama video of a room whose camera tilts by 4 to 19
    degrees comes out level, each frame close to the room rendered level along its heading
    (the same minimal turn), where the video as it is lies far from it."""
    from tests.frontend.test_lines import _tilting_video
    from usf_graph.frontend import render
    from usf_graph.geometry import level_rotation

    cam = cameras.Equirectangular(256, 128)
    video = _tilting_video([cam])
    writer = cv2.VideoWriter(str(tmp_path / "tilt.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 5, (256, 128))
    for ims, _ in video:
        writer.write(ims[0][..., ::-1].copy())
    writer.release()
    base = ["render", str(tmp_path / "tilt.avi"), "--camera", "equirectangular",
            "--to", "equirectangular:256x128"]
    assert main([*base, "--level-each", "--out", str(tmp_path / "level.avi")]) == 0
    out = capsys.readouterr().out
    assert "leveled by its own straight lines" in out and "built 6 times for 6 frames" in out
    tilts = [math.degrees(math.acos(up[2])) for _, up in video]  # 4 to 19 degrees
    lo, hi = map(float, re.search(r"up ([\d.]+) to ([\d.]+) degrees off level", out).groups())
    assert abs(lo - min(tilts)) < 1.5 and abs(hi - max(tilts)) < 1.5
    got, _ = decode_video(tmp_path / "level.avi")
    off, tilted = [], []
    for g, (ims, up) in zip(got, video):
        truth = render(ims[0], cam.turned(level_rotation(up)), cam)  # leveled by the true up
        off.append(np.abs(g.astype(float) - truth).mean())
        tilted.append(np.abs(ims[0].astype(float) - truth).mean())
    assert max(off) < 4.5  # Motion JPEG twice (3.2-3.4 here)
    assert min(tilted[2:]) > 2.5 * max(off)  # the tilt (10 degrees and more) was there to remove
    for extra, why in ((["--level"], "not with --level"), (["--imu", "/imu"], "not with")):
        assert main([*base, "--level-each", *extra, "--out", str(tmp_path / "x.avi")]) == 2
        assert why in capsys.readouterr().err
    cv2.imwrite(str(tmp_path / "one.png"), video[0][0][0])
    assert main(["render", str(tmp_path / "one.png"), "--camera", "equirectangular", "--to",
                 "equirectangular", "--level-each", "--out", str(tmp_path / "x.png")]) == 2
    assert "videos or a bag" in capsys.readouterr().err


def test_camera_overlay_draws_the_graticule_on_the_cameras_image(tmp_path, capsys):
    from usf_graph.viz import draw_graticule

    cv2.imwrite(str(tmp_path / "pano.png"), np.zeros((360, 720, 3), np.uint8))
    assert main(["camera", "equirectangular", "--overlay", str(tmp_path / "pano.png"),
                 str(tmp_path / "g.png")]) == 0  # a panorama's size from the image
    got = cv2.imread(str(tmp_path / "g.png"))[..., ::-1]
    assert np.array_equal(got, draw_graticule(np.zeros((360, 720, 3), np.uint8), cameras.Equirectangular(720, 360)))
    pin = cameras.Pinhole(256.0, 256.0, 255.5, 191.5, 512, 384)
    pin.save(tmp_path / "pin.yaml")
    cv2.imwrite(str(tmp_path / "half.png"), np.zeros((192, 256, 3), np.uint8))  # resized as a whole
    assert main(["camera", str(tmp_path / "pin.yaml"), "--overlay", str(tmp_path / "half.png"),
                 str(tmp_path / "h.png")]) == 0
    assert "scaling the calibration by 0.5" in capsys.readouterr().out
    want = draw_graticule(np.zeros((192, 256, 3), np.uint8), pin.resized(256, 192))
    assert np.array_equal(cv2.imread(str(tmp_path / "h.png"))[..., ::-1], want)
    assert main(["camera", str(tmp_path / "pin.yaml"), "--all", "--overlay", str(tmp_path / "half.png"),
                 str(tmp_path / "h.png")]) == 2


def test_render_level_straightens_a_tilted_panorama(tmp_path, capsys):
    """``render --level``: up from the panorama's straight lines (or ``--up``), and the
    target turned so that it is level: a panorama with its horizon straight, a pinhole
    upright, a rig's stitched panorama; each matches the room rendered level along the
    heading kept."""
    from usf_graph.frontend.lines import lines_up
    from usf_graph.geometry import level_rotation, rotation_from_axis_angle
    from usf_graph.scenes import make_room, render

    cam = cameras.Equirectangular(256, 128)
    scene = make_room(seed=3, index=3, materials="by_kind")
    pos, R0 = scene.viewpoint(0)
    T = rotation_from_axis_angle(np.array([0.0, 1.0, 0.0]), math.radians(15)) \
        @ rotation_from_axis_angle(np.array([1.0, 0.0, 0.0]), math.radians(-8))
    up = T.T @ [0.0, 0.0, 1.0]
    cv2.imwrite(str(tmp_path / "tilted.png"), render(scene, cam, pos, R0 @ T, boxes=False).rgb[..., ::-1])
    level = R0 @ T @ level_rotation(up).T  # the room level, along the heading the turn keeps
    pin = cameras.Pinhole(64.0, 64.0, 63.5, 63.5, 128, 128)
    pin.save(tmp_path / "pin.yaml")
    # the estimate is 0.7 degrees off here, enough to fail the pinhole's finer comparison
    for to, flags in (("equirectangular", []), ("equirectangular", ["--up", *map(str, up)]),
                      (str(tmp_path / "pin.yaml"), ["--up", *map(str, up)])):
        assert main(["render", str(tmp_path / "tilted.png"), "--camera", "equirectangular",
                     "--to", to, "--level", *flags, "--out", str(tmp_path / "out.png")]) == 0
        said = capsys.readouterr().out
        assert ("up given" if flags else "up from the straight lines") in said
        off = float(re.search(r"which is ([\d.]+) degrees off level", said).group(1))
        assert abs(off - math.degrees(math.acos(up[2]))) < (0.05 if flags else 0.5)  # T's 17.0
        out = cv2.imread(str(tmp_path / "out.png"))[..., ::-1].astype(float)
        target = cam if to == "equirectangular" else pin
        truth = render(scene, target, pos, level, boxes=False).rgb
        assert np.median(np.abs(out - truth).mean(-1)) < 2.0
        if target is cam:  # its verticals are columns again (a 90-degree view has too few lines)
            assert np.degrees(np.arccos(lines_up(out.astype(np.uint8), cam)[2])) < 1.5
    assert main(["render", str(tmp_path / "tilted.png"), "--camera", "equirectangular", "--to",
                 "equirectangular", "--up", "0", "0", "1", "--out", str(tmp_path / "o.png")]) == 2
    assert "add --level" in capsys.readouterr().err
    # lift --level: the signal on the grid, in the level frame
    cv2.imwrite(str(tmp_path / "truth.png"), render(scene, cam, pos, level, boxes=False).rgb[..., ::-1])
    for name, image, flags in (("leveled", "tilted", ["--level"]), ("truth", "truth", []),
                               ("tilted", "tilted", [])):
        assert main(["lift", str(tmp_path / f"{image}.png"), "--camera", "equirectangular", "--grid",
                     "icosahedral:4", *flags, "--out", str(tmp_path / f"{name}.pt")]) == 0
    got, want, raw = (load_lifted(tmp_path / f"{n}.pt").x for n in ("leveled", "truth", "tilted"))
    assert "degrees off level" in capsys.readouterr().out
    err = (got - want).abs().mean(-1)
    assert float(err.median()) < 3.0 and float(err.mean()) < 0.3 * float((raw - want).abs().mean())
    # a rig's images (two back-to-back fisheyes, the tilted room from their centre): up from
    # both cameras' lines together, the stitched panorama level
    shots = []
    for n, c in cameras.load_rig(FIXTURES / "kalibr_rig.yaml").items():
        shots.append(str(tmp_path / f"{n}.png"))
        c = c.with_fov(190).with_position(None)  # stitched at infinity: no parallax
        cv2.imwrite(shots[-1], render(scene, c, pos, R0 @ T, boxes=False).rgb[..., ::-1])
    assert main(["render", *shots, "--camera", str(FIXTURES / "kalibr_rig.yaml"), "--fov", "190",
                 "--level", "--to", "equirectangular:256x128", "--out", str(tmp_path / "rig_level.png")]) == 0
    said = capsys.readouterr().out
    off = float(re.search(r"rig's sphere frame, which is ([\d.]+) degrees off level", said).group(1))
    assert abs(off - math.degrees(math.acos(up[2]))) < 1.0
    out = cv2.imread(str(tmp_path / "rig_level.png"))[..., ::-1].astype(float)
    truth = render(scene, cam, pos, level, boxes=False).rgb
    assert np.median(np.abs(out - truth).mean(-1)) < 2.0  # 0.7 here
    assert main(["render", *shots, "--camera", str(FIXTURES / "kalibr_rig.yaml"), "--fov", "190",
                 "--to", "equirectangular:256x128", "--out", str(tmp_path / "rig_tilted.png")]) == 0
    tilted = cv2.imread(str(tmp_path / "rig_tilted.png"))[..., ::-1].astype(float)
    assert np.abs(tilted - truth).mean() > 4 * np.abs(out - truth).mean()  # the tilt was there


def test_cache_command_shows_and_clears(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("USF_GRAPH_CACHE", str(tmp_path / "c"))
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "lift-abc.npz").write_bytes(b"x" * 1_500_000)
    (tmp_path / "c" / "lift-abd.npz").write_bytes(b"x" * 20_000)
    (tmp_path / "c" / "graph-def.npz").write_bytes(b"x" * 3000)
    assert main(["cache"]) == 0
    out = capsys.readouterr().out
    assert str(tmp_path / "c") in out
    assert "  lift         2 files       1.52 MB\n" in out and "  graph        1 files       0.00 MB\n" in out
    assert "  total        3 files       1.52 MB\n" in out
    assert main(["cache", "--clear"]) == 0
    assert "removed 3 files" in capsys.readouterr().out and not list((tmp_path / "c").iterdir())
    monkeypatch.setenv("USF_GRAPH_CACHE", "off")
    assert main(["cache"]) == 0 and "off" in capsys.readouterr().out


def test_every_command_and_option_has_help(capsys):
    parser = build_parser()
    subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert set(subs.choices) == {"info", "camera", "bag", "lift", "render", "scenes", "cache", "train", "eval",
                                 "predict", "targets", "export"}
    for name, sub in subs.choices.items():
        assert sub.description, name
        for a in sub._actions:
            assert a.help and a.help.strip(), f"usf-graph {name} {a.dest} has no help"
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    assert "``" not in text and "lift" in text
    with pytest.raises(SystemExit):
        main(["lift", "--help"])
    text = capsys.readouterr().out
    for word in ("icosahedral:L", "healpix:NSIDE", "bilinear", "Kalibr", "equirectangular",
                 "(default: icosahedral:6)", "--image-mask", "--fov"):
        assert word in text, word
    assert "(default: None)" not in text and "(default: False)" not in text


def test_help_shows_a_default_unless_empty_or_already_said():
    from usf_graph.cli import _Help

    p = argparse.ArgumentParser(formatter_class=_Help)
    for flag, default, words in (("--a", 5, "rooms"), ("--b", None, "rooms"), ("--c", False, "on"),
                                 ("--d", 7, "rooms (default: seven)")):
        p.add_argument(flag, default=default, help=words)
    text = " ".join(p.format_help().split())
    assert "--a A rooms (default: 5)" in text and "--b B rooms --c C on --d D rooms (default: seven)" in text


def test_a_command_builds_only_its_own_options_and_help_imports_no_torch():
    """``usf-graph COMMAND ...`` parses as the whole parser does, its command's options
    only; ``usf-graph --help`` imports neither torch nor PyG (0.2 s, not 4.6), nor do the
    help screens of lift, render, predict, export, train and eval."""
    import subprocess
    import sys

    def options(parser):
        subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        return {n: sorted((a.dest, tuple(a.option_strings), repr(a.default)) for a in p._actions)
                for n, p in subs.choices.items()}

    whole = options(build_parser())
    for name in whole:
        alone = options(build_parser(name))
        assert alone[name] == whole[name], name
        assert all(alone[n] == [("help", ("-h", "--help"), repr(argparse.SUPPRESS))] for n in alone if n != name)
    # nor does the help of the commands a user runs most (train's reads the protocols'
    # defaults from their source)
    code = ("import sys\nfrom usf_graph.cli import main\nfor argv in ([], ['lift'], ['render'], "
            "['predict'], ['export'], ['train'], ['eval']):\n    try:\n        main(argv + ['--help'])\n"
            "    except SystemExit as e:\n        assert e.code == 0\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'torch_geometric')))")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    assert out.strip().splitlines()[-1] == "[]" and "COMMAND" in out and "--interpolation" in out
    assert "(det 0.002, seg 0.003)" in out and "--rotate" in out


def test_a_calibration_is_scaled_to_an_image_resized_as_a_whole(tmp_path, capsys):
    """A half-size frame of a calibrated camera lifts through the calibration scaled to it
    (with a note); a frame of another aspect ratio (a crop) is refused as before."""
    cam = cameras.KannalaBrandt(60.0, 60.0, 79.5, 59.5, 160, 120, k=(0.01, 0, 0, 0))
    cam.save(tmp_path / "cam.yaml")
    img = (np.random.default_rng(0).random((60, 80, 3)) * 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "half.png"), img[..., ::-1])
    assert main(["lift", str(tmp_path / "half.png"), "--camera", str(tmp_path / "cam.yaml"),
                 "--grid", "icosahedral:3", "--out", str(tmp_path / "s.pt")]) == 0
    assert ("note: the image is 80x60 and the calibration 160x120: scaling the calibration "
            "by 0.5") in capsys.readouterr().out
    ref = SphericalFrontend(cam.resized(80, 60), grids.icosahedral(3))(img)
    assert torch.equal(load_lifted(tmp_path / "s.pt").x, ref.x)
    cv2.imwrite(str(tmp_path / "crop.png"), img[:50])
    assert main(["lift", str(tmp_path / "crop.png"), "--camera", str(tmp_path / "cam.yaml"),
                 "--grid", "icosahedral:3"]) == 2
    assert "camera.resized(W, H)" in capsys.readouterr().err


def test_lift_cli_reports_bad_input(tmp_path, capsys):
    cam = cameras.Pinhole(100.0, 100.0, 79.5, 59.5, 160, 120)
    cam.save(tmp_path / "cam.yaml")
    cv2.imwrite(str(tmp_path / "small.png"), np.zeros((60, 100), np.uint8))  # not a resize
    rc = main(["lift", str(tmp_path / "small.png"), "--camera", str(tmp_path / "cam.yaml"),
               "--grid", "icosahedral:3"])
    assert rc == 2
    assert "160" in capsys.readouterr().err
    assert main(["lift", str(tmp_path / "none.png"), "--camera", str(tmp_path / "cam.yaml")]) == 2
    assert f"image {tmp_path / 'none.png'} does not exist" in capsys.readouterr().err
    (tmp_path / "empty.png").write_bytes(b"")
    (tmp_path / "text.png").write_text("not a picture")
    for name in ("empty.png", "text.png"):
        assert main(["lift", str(tmp_path / name), "--camera", str(tmp_path / "cam.yaml")]) == 2
        err = capsys.readouterr().err
        assert err == f"usf-graph: error: cannot read image {tmp_path / name}: empty, or not an " \
                      "image format OpenCV reads\n"


def test_info_reports_versions_and_working_extensions(capsys):
    assert main(["info"]) == 0
    out = capsys.readouterr().out
    assert torch.__version__ in out
    assert "compiled extensions  load and run" in out
    assert "USF_GRAPH_CACHE" in out and f"torch threads        {torch.get_num_threads()}" in out


def test_info_describes_a_checkpoint(tmp_path, capsys):
    from usf_graph.models import (
        PlanarCNN,
        PlanarDetector,
        PlanarUNet,
        SphericalClassifier,
        SphericalDetector,
    )
    from usf_graph.train import save_checkpoint

    seg = tiny_seg_checkpoint(tmp_path / "seg.pt")
    save_checkpoint(tmp_path / "seg.pt", seg, {"model": "spherical_unet", **seg.config},
                    {"a": {"mIoU": 0.4567, "acc": 0.9}, "d": {"mIoU": 0.1234}},
                    extra={"data": {"dataset": "rooms", "seed": 3, "materials": "by_kind"}})
    assert main(["info", str(tmp_path / "seg.pt")]) == 0
    rows = dict(re.split(r"\s{2,}", ln, maxsplit=1) for ln in capsys.readouterr().out.splitlines())
    numbers = sum(v.numel() for v in seg.state_dict().values())
    assert rows["model"] == f"spherical_unet, {numbers:,} stored numbers"
    assert rows["input"] == "icosahedral:3 (642 points); gravity" and rows["classes"] == "13"
    assert rows["trained on"] == "dataset rooms, seed 3, materials by_kind"
    assert rows["(a)"] == "mIoU 45.67" and rows["(d)"] == "mIoU 12.34"
    assert rows["made by"].startswith(f"usf-graph {usf_graph.__version__}")
    det = SphericalDetector(12, input_level=3, head_level=2, min_level=1, channels=(4, 4, 4))
    save_checkpoint(tmp_path / "det.pt", det, det.config, {"c": {"AP50": 0.25, "AP": 0.1}})
    mnist = SphericalClassifier(level=2, channels=(4, 4))
    save_checkpoint(tmp_path / "mnist.pt", mnist, mnist.config, {"NR": 0.9512, "R": 0.9433})
    cnn = PlanarCNN()
    save_checkpoint(tmp_path / "cnn.pt", cnn, cnn.config, {"NR": 0.98})
    unet = PlanarUNet(channels=(4, 4), gray=True)
    save_checkpoint(tmp_path / "unet.pt", unet, {"model": "planar_unet", "size": 48, **unet.config}, {})
    pdet = PlanarDetector(height=32, width=96, channels=(4, 4))
    save_checkpoint(tmp_path / "pdet.pt", pdet, {"model": "planar_detector", **pdet.config}, {})
    for name, seen in (("unet", "96x48 panoramas; gray"), ("pdet", "96x32 panoramas")):
        assert main(["info", str(tmp_path / f"{name}.pt")]) == 0
        rows = dict(re.split(r"\s{2,}", ln, maxsplit=1) for ln in capsys.readouterr().out.splitlines())
        assert rows["input"] == seen, rows
    for name, model, test, score in (("det", "spherical_detector", "(c)", "AP50 25.00"),
                                     ("mnist", "spherical_classifier", "(R)", "accuracy 94.33"),
                                     ("cnn", "planar_cnn", "(NR)", "accuracy 98.00")):
        assert main(["info", str(tmp_path / f"{name}.pt")]) == 0
        rows = dict(re.split(r"\s{2,}", ln, maxsplit=1)
                    for ln in capsys.readouterr().out.splitlines())
        assert rows["model"].startswith(f"{model},") and rows[test] == score, rows
    (tmp_path / "bad.pt").write_bytes(b"junk")
    assert main(["info", str(tmp_path / "bad.pt")]) == 2
    assert "is not a readable usf-graph checkpoint" in capsys.readouterr().err


def test_info_exits_with_1_on_a_broken_installation(capsys, monkeypatch):
    """A required package that does not import, or extensions that do not run, is a broken
    installation: named, and exit status 1 (an optional one missing is not)."""
    import sys

    import torch_cluster

    with monkeypatch.context() as m:
        m.setitem(sys.modules, "healpy", None)  # import then raises ImportError
        assert main(["info"]) == 1
    assert "healpy               NOT AVAILABLE (ModuleNotFoundError: import of healpy halted; None in " \
           "sys.modules)" in capsys.readouterr().out

    def broken(*args, **kwargs):
        raise RuntimeError("undefined symbol: _ZN3c10")

    monkeypatch.setattr(torch_cluster, "radius_graph", broken)
    assert main(["info"]) == 1
    assert "compiled extensions  FAILED: undefined symbol: _ZN3c10" in capsys.readouterr().out


def test_info_says_how_to_get_the_optional_export_packages(capsys, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # import then raises ImportError
    assert main(["info"]) == 0  # optional: still a healthy install
    out = capsys.readouterr().out
    assert "onnxruntime          not installed (optional, for usf-graph export: pip install " in out


def test_camera_cli_prints_field_of_view_and_plots(tmp_path, capsys):
    path = "tests/fixtures/ros_equidistant.yaml"
    cam = cameras.load(path)
    assert main(["camera", path, "--plot", str(tmp_path / "lnm.png")]) == 0
    out = capsys.readouterr().out
    assert "KannalaBrandt" in out
    assert f"{cam.solid_angle():.4f} sr" in out and f"{cam.fov_deg:.2f} deg" in out
    assert (tmp_path / "lnm.png").stat().st_size > 20_000
    # a 180 degree equidistant fisheye, written in our own format, covers half the sphere
    cameras.Fisheye(150, 255.5, 255.5, 512, 512, fov_deg=180).save(tmp_path / "half.yaml")
    assert main(["camera", str(tmp_path / "half.yaml")]) == 0
    assert "of the sphere" in (line := capsys.readouterr().out.splitlines()[3])
    assert abs(float(line.split("=")[1].split("%")[0]) - 50.0) < 0.6
    # --resize: the calibration for half-size frames, saved and read back
    assert main(["camera", path, "--resize", "320x240", "--save", str(tmp_path / "s.yaml")]) == 0
    assert "image          320 x 240" in capsys.readouterr().out
    assert cameras.load(tmp_path / "s.yaml").key() == cam.resized(320, 240).key()
    assert main(["camera", path, "--resize", "320"]) == 2
    assert "bad --resize '320': write WIDTHxHEIGHT" in capsys.readouterr().err
    # one camera to COLMAP is camera 1; an unposed camera has no optical centre, a rig's has
    assert main(["camera", path, "--save-colmap", str(tmp_path / "cameras.txt")]) == 0
    out = capsys.readouterr().out
    assert "(COLMAP's camera list, 1 camera;" in out and "optical centre" not in out
    assert list(cameras.load_all(tmp_path / "cameras.txt")) == [1]
    assert main(["camera", "tests/fixtures/kalibr_rig.yaml", "--key", "cam1"]) == 0
    assert "optical centre (-0.1000, +0.0000, +0.0000) in the rig's" in capsys.readouterr().out


def test_camera_cli_reports_bad_files(tmp_path, capsys):
    (tmp_path / "bad.yaml").write_text("usf_graph_camera: 1\nmodel: Fancy\nparams: {}\n")
    assert main(["camera", str(tmp_path / "bad.yaml")]) == 2
    assert "Fancy" in capsys.readouterr().err
    (tmp_path / "odd.yaml").write_text("focal: 3\n")
    assert main(["camera", str(tmp_path / "odd.yaml")]) == 2
    assert "unrecognized calibration format" in capsys.readouterr().err
    assert main(["camera", str(tmp_path / "missing.yaml")]) == 2


@pytest.mark.parametrize("task", ["det", "seg"])
def test_train_passes_the_protocol_options_or_their_defaults(task, monkeypatch):
    """``train det|seg`` hands ``run`` each option as given, else ``run``'s own default."""
    module = importlib.import_module(f"usf_graph.train.{task}")
    defaults = inspect.signature(module.run).parameters
    calls = []

    @functools.wraps(module.run)  # the same signature, which the command reads
    def fake_run(**kw):
        calls.append(kw)
        return {}

    monkeypatch.setattr(module, "run", fake_run)
    assert main(["train", task]) == 0
    assert main(["train", task, "--fov-epochs", "0", "--up-epochs", "3", "--up-sign", "0.5",
                 "--num-train", "7", "--size", "32"]) == 0
    for key in ("fov_epochs", "up_epochs", "up_extra", "up_caps", "up_sign", "size",
                "num_train", "num_test", "epochs", "batch_size", "lr", "channel_scale"):
        assert calls[0][key] == defaults[key].default, key
    assert calls[1]["fov_epochs"] == 0 and calls[1]["up_epochs"] == 3 and calls[1]["up_sign"] == 0.5
    assert calls[1]["num_train"] == 7 and calls[1]["size"] == 32
    assert calls[1]["up_extra"] == defaults["up_extra"].default
    assert calls[1]["num_test"] == defaults["num_test"].default
    assert calls[0]["channel_scale"] == defaults["channel_scale"].default == 1.0
    assert main(["train", task, "--channel-scale", "0.5"]) == 0
    assert calls[2]["channel_scale"] == 0.5
    assert calls[0]["materials"] == defaults["materials"].default == "random"
    assert main(["train", task, "--materials", "by_kind"]) == 0
    assert calls[3]["materials"] == "by_kind"


@pytest.mark.parametrize("task", ["det", "seg"])
def test_eval_scores_a_checkpoint_on_rooms_of_its_own_materials(task, tmp_path, monkeypatch, capsys):
    from usf_graph.models import SphericalDetector, SphericalUNet
    from usf_graph.train import save_checkpoint

    module = importlib.import_module(f"usf_graph.train.{task}")
    seen = []

    def stop(*a, **kw):
        seen.append(kw["materials"])
        raise ValueError("stopped before rendering")

    monkeypatch.setattr(module, "protocol_sets", stop)
    net = SphericalDetector(12, input_level=3, head_level=2, min_level=1, channels=(4, 4, 4)) \
        if task == "det" else SphericalUNet(13, level=3, channels=(4, 4, 4, 4))
    cfg = net.config if task == "det" else {"model": "spherical_unet", **net.config}
    for materials in ("by_kind", "random", None):
        data = {"dataset": "rooms", "seed": 0} | ({"materials": materials} if materials else {})
        save_checkpoint(tmp_path / "m.pt", net, cfg, {}, extra={"data": data})
        assert main(["eval", task, str(tmp_path / "m.pt")]) == 2
        assert "stopped before rendering" in capsys.readouterr().err
    assert seen == ["by_kind", "random", "random"]  # not recorded: saved before materials existed


@pytest.mark.parametrize("task, dataset", [("det", "pandora"), ("seg", "stanford2d3ds"),
                                           ("seg", "woodscape")])
@pytest.mark.parametrize("option, value, said", [
    ("--channel-scale", "0.5", "--channel-scale is an option of the rooms protocols; on {}"),
    ("--materials", "random", "--materials is an option of the procedural rooms; {}'s"),
    ("--up-extra", "10", "--up-extra: options of the rooms protocols; {} trains on its own"),
    ("--num-train", "10", "--num-train: options of the rooms protocols; {} trains on its own"),
    ("--fov-epochs", "2", "--fov-epochs: options of the rooms protocols; {} trains on its own"),
    ("--fov-epochs", "0", "--fov-epochs: options of the rooms protocols"),  # 0 is given too
    ("--up-sign", "0", "--up-sign: options of the rooms protocols")])
def test_rooms_options_are_refused_on_real_data(task, dataset, option, value, said, capsys):
    assert main(["train", task, "--dataset", dataset, option, value]) == 2
    assert said.format(dataset) in capsys.readouterr().err


@pytest.mark.parametrize("option", ["--num-train", "--num-test", "--size"])
def test_train_refuses_sizes_and_counts_below_one(option, capsys):
    with pytest.raises(SystemExit):
        main(["train", "seg", option, "0"])
    assert f"{option}: must be at least 1, got 0" in capsys.readouterr().err


@pytest.mark.parametrize("argv, said", [
    (["train", "det", "--epochs", "-1"], "--epochs: must be at least 1, got -1"),
    (["train", "seg", "--epochs", "0"], "--epochs: must be at least 1, got 0"),  # was the default
    (["train", "mnist", "--batch-size", "0"], "--batch-size: must be at least 1, got 0"),
    (["train", "seg", "--lr", "0"], "--lr: must be above 0.0, got 0"),
    (["train", "det", "--lr", "nan"], "--lr: must be above 0.0, got nan"),
    (["train", "seg", "--up-caps", "1.5"], "--up-caps: must be at least 0.0 and at most 1.0"),
    (["train", "det", "--fov-epochs", "-2"], "--fov-epochs: must be at least 0, got -2"),
    (["train", "det", "--up-epochs", "0"], "--up-epochs: must be at least 1, got 0"),
    (["train", "mnist", "--level", "-1"], "--level: must be at least 0, got -1"),
    (["scenes", "--num", "0", "--out", "x"], "--num: must be at least 1, got 0"),
    (["eval", "det", "x.pt", "--level-prior", "-1"], "--level-prior: must be at least 0.0"),
    (["predict", "det", "x.pt", "y.png", "--camera", "equirectangular", "--min-score", "2"],
     "--min-score: must be at least 0.0 and at most 1.0, got 2"),
    (["predict", "seg", "x.pt", "y.mp4", "--camera", "equirectangular", "--video", "o.mp4",
      "--video-fps", "0"], "--video-fps: must be above 0.0, got 0"),
    (["render", "x.bag", "--to", "equirectangular", "--out", "x.mp4", "--fps", "0"],
     "--fps: must be above 0.0, got 0")])
def test_numbers_out_of_range_stop_at_the_command_line(argv, said, capsys):
    with pytest.raises(SystemExit):
        main(argv)
    assert said in capsys.readouterr().err


@pytest.mark.parametrize("argv, missing", [
    ([], "COMMAND"), (["lift", "x.png"], "--camera"), (["render", "x.png", "--out", "y.png"], "--to"),
    (["render", "x.png", "--to", "equirectangular"], "--out"), (["scenes"], "--out")])
def test_required_options_are_named_when_missing(argv, missing, capsys):
    with pytest.raises(SystemExit):
        main(argv)
    assert f"the following arguments are required: {missing}" in capsys.readouterr().err


def test_scenes_default_to_seed_0_and_say_what_each_room_holds(tmp_path, capsys):
    from usf_graph.scenes import make_room, render
    from usf_graph.scenes.lenses import protocol_cameras

    assert main(["scenes", "--out", str(tmp_path), "--num", "1", "--size", "16"]) == 0
    room = make_room(0, 0)
    boxes = render(room, protocol_cameras(16)["equirectangular"]).boxes
    assert (f"room 0: {room.size[0]:.1f} x {room.size[1]:.1f} x {room.size[2]:.1f} m, "
            f"{len(room.instances)} instances, {len(boxes)} boxes in the panorama") in capsys.readouterr().out


def test_train_and_eval_mnist_take_the_protocols_folders_by_default(monkeypatch, capsys):
    from usf_graph.train import mnist

    calls = []
    monkeypatch.setattr(mnist, "run", functools.wraps(mnist.run)(lambda **kw: calls.append(kw) or {}))
    assert main(["train", "mnist"]) == 0  # {}: a torchrun rank other than 0, which prints nothing
    assert calls[0]["root"] == "data/mnist" and calls[0]["out"] == "runs/mnist"

    def score(path, **kw):
        calls.append(kw)
        return {"provenance": None, "model": "spherical", "rotate": "so3", "seed": 0, "acc": 0.5, "loss": 1.0}

    monkeypatch.setattr(mnist, "score", functools.wraps(mnist.score)(score))
    assert main(["eval", "mnist", "m.pt"]) == 0
    assert calls[1]["root"] == "data/mnist" and "accuracy 50.00%, loss 1.0000" in capsys.readouterr().out


def _make_n(*targets, **variables) -> str:
    """What ``make`` would run for ``targets`` (``make -n``: printed, not run), variables
    expanded, the set-up step left out."""
    import subprocess
    from pathlib import Path

    out = subprocess.run(["make", "-n", "-s", *targets, *(f"{k}={v}" for k, v in variables.items())],
                         cwd=Path(__file__).resolve().parents[1], capture_output=True, text=True,
                         check=True).stdout
    return "\n".join(ln for ln in out.splitlines() if "bootstrap.sh" not in ln)


def test_make_protocols_runs_every_table_run_once_then_the_targets(tmp_path):
    """``make protocols``' recipe with a stand-in ``usf-graph`` that logs its arguments: each
    run of the README's tables with the recipes of the demos, the materials and device
    asked for; a run with results.json is not run again."""
    import subprocess

    (tmp_path / "v" / "bin").mkdir(parents=True)
    fake = tmp_path / "v" / "bin" / "usf-graph"
    fake.write_text(f'#!/bin/sh\necho "$@" >> {tmp_path}/log\n')
    fake.chmod(0o755)
    (tmp_path / "r" / "det15_seed2").mkdir(parents=True)
    (tmp_path / "r" / "det15_seed2" / "results.json").write_text("{}")
    recipe = _make_n("protocols", VENV=tmp_path / "v", MATERIALS="by_kind", DEVICE="cuda", RUNS=tmp_path / "r")
    subprocess.run(["bash", "-c", recipe], check=True)
    calls = (tmp_path / "log").read_text().splitlines()
    train = [c for c in calls if c.startswith("train")]
    outs = [c.split("--out ")[1] for c in train]
    assert outs == [f"{tmp_path}/r/{n}" for n in ("det15_seed0", "det15_seed1", "det15_seed3", "det15_seed4",
                                                   "det_full", "seg15_seed0", "seg15_seed1", "seg15_seed2",
                                                   "seg_full")]
    det15 = "--channel-scale 0.5 --epochs 16 --fov-epochs 3 --up-epochs 4 --up-extra 400"
    seg15 = "--channel-scale 0.5 --epochs 6 --fov-epochs 2 --up-epochs 4 --up-extra 400"
    tail = "--materials by_kind --device cuda --resume --out"
    assert train[0] == f"train det {det15} --seed 0 {tail} {outs[0]}"
    assert train[4] == f"train det {tail} {outs[4]}"
    assert train[6] == f"train seg {seg15} --seed 1 {tail} {outs[6]}"
    assert train[8] == f"train seg {tail} {outs[8]}"
    assert calls[-2].split() == ["targets"] + [f"{tmp_path}/r/det15_seed{s}" for s in range(5)] + \
        [f"{tmp_path}/r/det_full"]
    assert calls[-1].split() == ["targets"] + [f"{tmp_path}/r/seg15_seed{s}" for s in range(3)] + \
        [f"{tmp_path}/r/seg_full"]


def test_the_makefile_demos_of_the_protocols_parse(monkeypatch):
    """Each ``make demo-*`` line of the rooms protocols reaches ``run`` with its options."""
    import shlex

    lines = [ln.split("usf-graph ", 1)[1] for ln in _make_n("demo-det", "demo-det-full", "demo-seg",
                                                          "demo-seg-full").splitlines()
             if "usf-graph train" in ln]
    assert len(lines) == 4, lines  # each protocol's 15-minute recipe and its full one
    calls = []
    for task in ("det", "seg"):
        module = importlib.import_module(f"usf_graph.train.{task}")

        @functools.wraps(module.run)
        def fake_run(_task=task, **kw):
            calls.append((_task, kw))
            return {}

        monkeypatch.setattr(module, "run", fake_run)
    for ln in lines:
        assert main(shlex.split(ln)) == 0, ln
    recipes = {kw["out"]: (task, kw["channel_scale"], kw["epochs"], kw["fov_epochs"], kw["up_extra"])
               for task, kw in calls}
    assert recipes["runs/seg_15min"] == ("seg", 0.5, 6, 2, 400)
    assert recipes["runs/det_15min"] == ("det", 0.5, 16, 3, 400)
    assert recipes["runs/seg"][1:] == (1.0, 8, 6, 800) and recipes["runs/det"][1:] == (1.0, 24, 6, 1600)


def test_predict_cli_on_a_camera_file_seg_and_det(tmp_path, capsys):
    """``predict`` reads a PNG (OpenCV's BGR) and a camera file, and writes what
    ``train.apply`` returns for the RGB array: a label image, and boxes in PANDORA's form."""
    import json

    from usf_graph.models import PlanarUNet, SphericalDetector
    from usf_graph.ops import canonical_boxes, to_pandora
    from usf_graph.scenes import DETECTION_CLASSES
    from usf_graph.train import save_checkpoint
    from usf_graph.train.apply import UNSEEN, detect_image, segment_image
    from usf_graph.train.seg import protocol_sets

    ds = protocol_sets(tmp_path / "rooms", size=32, level=3, num_train=0, num_test=1,
                       tests=("c",), progress=False)["c"]
    rgb = ds.image[0].numpy()
    cv2.imwrite(str(tmp_path / "view.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    ds.camera.save(tmp_path / "fish.yaml")
    seg = tiny_seg_checkpoint(tmp_path / "seg.pt", size=32)
    common = ["--camera", str(tmp_path / "fish.yaml"), "--out", str(tmp_path / "out"),
              "--interpolation", "bilinear"]
    assert main(["predict", "seg", str(tmp_path / "seg.pt"), str(tmp_path / "view.png"), *common]) == 0
    out = capsys.readouterr().out
    assert "estimated, margin" in out and "view: " in out and "%" in out
    got = cv2.imread(str(tmp_path / "out" / "view_labels.png"), cv2.IMREAD_UNCHANGED)
    want = segment_image(seg.eval(), rgb, ds.camera, interpolation="bilinear")["labels"]
    assert got.dtype == np.uint8 and np.array_equal(got, want)
    assert len(np.unique(want)) > 2 and (tmp_path / "out" / "view_seg.png").stat().st_size > 0
    seen = want[want != UNSEEN]  # the line names the five largest shares of the seen pixels
    shares = np.sort(np.bincount(seen) / seen.size)[::-1][:5]
    line = next(s for s in out.splitlines() if s.startswith("view: "))
    printed = [float(v) for v in re.findall(r" (\d+\.\d)%", line)]
    assert printed == pytest.approx(100 * shares[shares > 0], abs=0.051)
    assert main(["predict", "seg", str(tmp_path / "seg.pt"), str(tmp_path / "view.png"), *common,
                 "--up", "0", "0", "2"]) == 0
    assert "up: (+0.000, +0.000, +1.000), given" in capsys.readouterr().out
    assert main(["predict", "seg", str(tmp_path / "seg.pt"), str(tmp_path / "view.png"), *common,
                 "--render", "soft"]) == 0
    soft = segment_image(seg, rgb, ds.camera, interpolation="bilinear", render="soft")["labels"]
    got = cv2.imread(str(tmp_path / "out" / "view_labels.png"), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(got, soft) and np.array_equal(soft == UNSEEN, want == UNSEEN)
    capsys.readouterr()
    # frames: the model loaded once, an output per image; one name twice is refused
    (tmp_path / "frames").mkdir()
    cv2.imwrite(str(tmp_path / "frames" / "next.png"), cv2.cvtColor(rgb[:, ::-1].copy(), cv2.COLOR_RGB2BGR))
    frames = [str(tmp_path / "view.png"), str(tmp_path / "frames" / "next.png")]
    assert main(["predict", "seg", str(tmp_path / "seg.pt"), *frames, *common]) == 0
    assert capsys.readouterr().out.count("== ") == 2
    flipped = segment_image(seg, rgb[:, ::-1].copy(), ds.camera, interpolation="bilinear")["labels"]
    assert np.array_equal(cv2.imread(str(tmp_path / "out" / "next_labels.png"), cv2.IMREAD_UNCHANGED), flipped)
    assert not np.array_equal(flipped, want)
    assert main(["predict", "seg", str(tmp_path / "seg.pt"), frames[0], frames[0], *common]) == 2
    assert "several images are named ['view']" in capsys.readouterr().err
    # a video: every N-th frame, read as OpenCV decodes it, its own outputs
    h, w = rgb.shape[:2]
    video = cv2.VideoWriter(str(tmp_path / "drive.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 5, (w, h))
    for k in range(5):
        video.write(cv2.cvtColor(np.roll(rgb, 3 * k, axis=1), cv2.COLOR_RGB2BGR))
    video.release()
    assert main(["predict", "seg", str(tmp_path / "seg.pt"), str(tmp_path / "drive.avi"), *common,
                 "--every", "2"]) == 0
    assert capsys.readouterr().out.count("== ") == 3
    cap = cv2.VideoCapture(str(tmp_path / "drive.avi"))
    decoded = [cv2.cvtColor(cap.read()[1], cv2.COLOR_BGR2RGB) for _ in range(5)]
    for k in (0, 2, 4):
        want_k = segment_image(seg, decoded[k], ds.camera, interpolation="bilinear")["labels"]
        got_k = cv2.imread(str(tmp_path / "out" / f"drive_{k:06d}_labels.png"), cv2.IMREAD_UNCHANGED)
        assert np.array_equal(got_k, want_k)
    assert not (tmp_path / "out" / "drive_000001_labels.png").exists()
    (tmp_path / "broken.mp4").write_bytes(b"not a video")
    for argv, said in (([str(tmp_path / "broken.mp4")], "cannot read video"),
                       ([frames[0], "--every", "2"], "--every picks a video's or a bag's frames"),
                       ([str(tmp_path / "drive.avi"), "--rig"], "not videos"),
                       ([frames[0], "--min-score", "0.5"], "--min-score is detection's"),
                       ([frames[0], "--video-fps", "5"], "--video-fps is --video's frame rate")):
        assert main(["predict", "seg", str(tmp_path / "seg.pt"), *argv, *common]) == 2
        assert said in capsys.readouterr().err, said

    det = SphericalDetector(12, input_level=3, head_level=2, min_level=1, channels=(8, 8, 8),
                            gravity=True)
    with torch.no_grad():
        det.head.bias[:12].fill_(0.0)  # heatmaps over the 0.05 the JSON keeps from
    save_checkpoint(tmp_path / "det.pt", det, det.config, {})
    assert main(["predict", "det", str(tmp_path / "det.pt"), str(tmp_path / "view.png"), *common,
                 "--min-score", "0"]) == 0
    doc = json.loads((tmp_path / "out" / "view_boxes.json").read_text())
    r = detect_image(det.eval(), rgb, ds.camera, interpolation="bilinear")
    assert len(doc["detections"]) == len(r["boxes"]) > 0
    bbox = np.array([d["bbox"] for d in doc["detections"]])
    assert np.allclose(bbox, to_pandora(canonical_boxes(r["boxes"])), atol=1e-9)
    assert (np.abs(bbox[:, 4]) <= 45 + 1e-9).all()
    assert [d["category"] for d in doc["detections"]] == [DETECTION_CLASSES[c] for c in r["classes"]]
    drawn = cv2.imread(str(tmp_path / "out" / "view_boxes.png"))
    assert drawn.shape == (512, 512, 3)  # a 32-pixel view, enlarged to draw on
    assert f"{len(r['boxes'])} of {len(r['boxes'])} boxes" in capsys.readouterr().out

    planar = PlanarUNet(13, channels=(4, 4))
    save_checkpoint(tmp_path / "planar.pt", planar, {"model": "planar_unet", **planar.config}, {})
    assert main(["predict", "seg", str(tmp_path / "planar.pt"), str(tmp_path / "view.png"), *common]) == 2
    assert "not a spherical seg model" in capsys.readouterr().err
    assert main(["predict", "det", str(tmp_path / "seg.pt"), str(tmp_path / "view.png"), *common]) == 2
    assert "not a spherical det model" in capsys.readouterr().err
    assert main(["predict", "det", str(tmp_path / "det.pt"), str(tmp_path / "view.png"), *common,
                 "--render", "soft"]) == 2
    assert "--render is segmentation's" in capsys.readouterr().err


def test_predict_reads_an_alpha_channel_as_an_image_mask(tmp_path, capsys):
    """An RGBA image's fully transparent pixels are left out, as ``--image-mask`` leaves them:
    the labels equal those of the RGB image with that mask, whatever the hidden pixels hold."""

    ds = _fisheye_views(tmp_path)
    rgb = ds.image[0].numpy()
    ds.camera.save(tmp_path / "fish.yaml")
    hidden = np.zeros(rgb.shape[:2], bool)
    hidden[:, : rgb.shape[1] // 3] = True  # the left third, e.g. the robot's body
    rgba = np.dstack([np.where(hidden[..., None], 255, rgb), np.where(hidden, 0, 255)]).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "rgba.png"), cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
    cv2.imwrite(str(tmp_path / "rgb.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(tmp_path / "mask.png"), np.where(hidden, 0, 255).astype(np.uint8))
    tiny_seg_checkpoint(tmp_path / "seg.pt", size=32)
    common = ["--camera", str(tmp_path / "fish.yaml"), "--interpolation", "bilinear"]
    assert main(["predict", "seg", str(tmp_path / "seg.pt"), str(tmp_path / "rgba.png"), *common,
                 "--out", str(tmp_path / "a")]) == 0
    assert f"hides {int(hidden.sum())} pixels" in capsys.readouterr().out
    assert main(["predict", "seg", str(tmp_path / "seg.pt"), str(tmp_path / "rgb.png"), *common,
                 "--out", str(tmp_path / "b"), "--image-mask", str(tmp_path / "mask.png")]) == 0
    a = cv2.imread(str(tmp_path / "a" / "rgba_labels.png"), cv2.IMREAD_UNCHANGED)
    b = cv2.imread(str(tmp_path / "b" / "rgb_labels.png"), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(a, b) and (a[hidden] == 255).all() and (a[~hidden] != 255).any()


def _fisheye_views(tmp_path):
    from usf_graph.train.seg import protocol_sets

    return protocol_sets(tmp_path / "rooms", size=32, level=3, num_train=0, num_test=1,
                         tests=("c",), progress=False)["c"]


def test_a_rigs_pictures_of_other_sizes_are_stacked_at_the_first_ones_scale():
    from usf_graph.cli_predict import _stacked

    a, b = np.zeros((10, 20, 3), np.uint8), np.full((20, 40, 3), 200, np.uint8)
    v = _stacked([a, b], axis=0)  # one above the other: b at a's width
    assert v.shape == (20, 20, 3) and (v[:10] == 0).all() and (v[10:] == 200).all()
    h = _stacked([a, b], axis=1)  # side by side: b at a's height
    assert h.shape == (10, 40, 3) and (h[:, :20] == 0).all() and (h[:, 20:] == 200).all()


def test_predict_cli_on_a_rig(tmp_path, capsys):
    """``predict --rig``: one frame of a Kalibr camchain's cameras, one sphere, an answer
    per camera, as ``train.apply`` gives it for the rig."""
    from usf_graph.frontend import render
    from usf_graph.train import save_checkpoint
    from usf_graph.train.apply import segment_image
    from usf_graph.viz import labelled_panorama

    rig = {n: c.with_fov(190) for n, c in cameras.load_rig(FIXTURES / "kalibr_rig.yaml").items()}
    pano = labelled_panorama(256, 128)
    paths = []
    for name, cam in rig.items():
        im = (255 * render(pano, cameras.Equirectangular(256, 128), cam)).round().astype(np.uint8)
        paths.append(str(tmp_path / f"{name}.png"))
        cv2.imwrite(paths[-1], cv2.cvtColor(im, cv2.COLOR_RGB2BGR))
    seg = tiny_seg_checkpoint(tmp_path / "seg.pt")
    argv = ["predict", "seg", str(tmp_path / "seg.pt"), *paths, "--rig", "--camera",
            str(FIXTURES / "kalibr_rig.yaml"), "--fov", "190", "--out", str(tmp_path / "out")]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert out.count("up: (") == 1 and "cam0: " in out and "cam1: " in out  # one sphere
    rgb = [cv2.cvtColor(cv2.imread(p), cv2.COLOR_BGR2RGB) for p in paths]
    want = segment_image(seg.eval(), rgb, rig)["labels"]
    for name, lab in zip(rig, want):
        assert np.array_equal(cv2.imread(str(tmp_path / "out" / f"{name}_labels.png"),
                                         cv2.IMREAD_UNCHANGED), lab)
    # --split: a frame with both cameras side by side, and a video of such frames (MJPG:
    # its frames are checked against what the library gives on the decoded frames)
    dual = np.concatenate([cv2.imread(p) for p in paths], 1)
    cv2.imwrite(str(tmp_path / "dual.png"), dual)
    split = ["--rig", "--split", "--camera", str(FIXTURES / "kalibr_rig.yaml"), "--fov", "190",
             "--out", str(tmp_path / "split")]
    assert main(["predict", "seg", str(tmp_path / "seg.pt"), str(tmp_path / "dual.png"), *split]) == 0
    for name, lab in zip(rig, want):
        assert np.array_equal(cv2.imread(str(tmp_path / "split" / f"dual_{name}_labels.png"),
                                         cv2.IMREAD_UNCHANGED), lab)
    video = cv2.VideoWriter(str(tmp_path / "dual.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 5,
                            (dual.shape[1], dual.shape[0]))
    for _ in range(2):
        video.write(dual)
    video.release()
    assert main(["predict", "seg", str(tmp_path / "seg.pt"), str(tmp_path / "dual.avi"), *split]) == 0
    cap = cv2.VideoCapture(str(tmp_path / "dual.avi"))
    frame = cv2.cvtColor(cap.read()[1], cv2.COLOR_BGR2RGB)
    cap.release()
    got = segment_image(seg.eval(), [frame[:, :400], frame[:, 400:]], rig)["labels"]
    assert np.array_equal(cv2.imread(str(tmp_path / "split" / "dual_000000_cam1_labels.png"),
                                     cv2.IMREAD_UNCHANGED), got[1])
    assert (tmp_path / "split" / "dual_000001_cam0_labels.png").exists()  # every frame
    capsys.readouterr()
    assert main(["predict", "seg", str(tmp_path / "seg.pt"), str(tmp_path / "dual.png"), "--split",
                 "--camera", str(FIXTURES / "kalibr_rig.yaml")]) == 2
    assert "add --rig" in capsys.readouterr().err
    # --up-lines reads both cameras' lines (the panorama's labels are text: few lines)
    assert main([*argv, "--up-lines"]) == 0
    lines_said = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("up: (")]
    assert len(lines_said) == 1 and ("straight-line axes" in lines_said[0] or "too few" in lines_said[0])
    # the detector on the rig: boxes in the rig's frame, drawn where each camera sees them
    import json

    from usf_graph.models import SphericalDetector
    from usf_graph.train.apply import detect_image

    det = SphericalDetector(12, input_level=3, head_level=2, min_level=1, channels=(8, 8, 8),
                            gravity=True)
    with torch.no_grad():
        det.head.bias[:12].fill_(0.0)
    save_checkpoint(tmp_path / "det.pt", det, det.config, {})
    assert main(["predict", "det", str(tmp_path / "det.pt"), *argv[3:], "--min-score", "0"]) == 0
    doc = json.loads((tmp_path / "out" / "cam0_boxes.json").read_text())
    r = detect_image(det.eval(), rgb, rig)
    assert doc["images"] == paths and len(doc["detections"]) == len(r["boxes"]) > 0
    drawn = [cv2.imread(str(tmp_path / "out" / f"{n}_boxes.png")) for n in rig]
    assert all(d.shape == (400, 400, 3) for d in drawn) and not np.array_equal(*drawn)
    assert main(argv[:3] + paths[:1] + argv[5:]) == 2
    assert "2 cameras (cam0, cam1) but 1 images" in capsys.readouterr().err
    assert main(argv + ["--key", "cam0"]) == 2
    assert "picks a rig in a COLMAP model; this file holds one rig" in capsys.readouterr().err
    # stitched at 2 m, as the library does it
    assert main(argv + ["--distance", "2"]) == 0
    want = segment_image(seg.eval(), rgb, cameras.stitch_at(rig, 2.0))["labels"]
    for name, lab in zip(rig, want):
        assert np.array_equal(cv2.imread(str(tmp_path / "out" / f"{name}_labels.png"),
                                         cv2.IMREAD_UNCHANGED), lab)
    assert main(argv[:3] + paths[:1] + ["--camera", str(FIXTURES / "kalibr_rig.yaml"),
                                        "--distance", "2"]) == 2
    assert "--distance stitches the cameras of a --rig" in capsys.readouterr().err


@pytest.mark.parametrize("task, module", [("mnist", "mnist"), ("seg", "seg"), ("det", "det"),
                                          ("seg", "stanford"), ("det", "pandora")])
def test_train_resume_reaches_the_run(monkeypatch, tmp_path, task, module):
    """``train --resume`` hands ``resume=True`` to the task's run (the runs and fit are
    tested for what resuming does: tests/train)."""
    import usf_graph.train.det as det
    import usf_graph.train.mnist as mnist
    import usf_graph.train.real as real
    import usf_graph.train.seg as seg

    target, fn = {"mnist": (mnist, "run"), "seg": (seg, "run"), "det": (det, "run"),
                  "stanford": (real, "run_stanford"), "pandora": (real, "run_pandora")}[module]
    seen = {}

    @functools.wraps(getattr(target, fn))  # its signature: the parser reads its defaults
    def fake(**kw):
        seen.update(kw)
        return {}

    monkeypatch.setattr(target, fn, fake)
    data = {"stanford": ["--dataset", "stanford2d3ds"], "pandora": ["--dataset", "pandora"]}
    for flag in ([], ["--resume"]):
        assert main(["train", task, "--out", str(tmp_path), *data.get(module, []), *flag]) == 0
        assert seen.pop("resume") is bool(flag)
    if task != "mnist":  # and --gray, gray=True
        assert seen.pop("gray") is False
        assert main(["train", task, "--out", str(tmp_path), *data.get(module, []), "--gray"]) == 0
        assert seen.pop("gray") is True
    if module != "det" and module != "pandora":  # mnist: the first conv's level; seg: the grid's
        assert seen.pop("level") == (4 if task == "mnist" else 5)  # run's default
        assert main(["train", task, "--out", str(tmp_path), *data.get(module, []), "--level", "3"]) == 0
        assert seen.pop("level") == 3
    if module == "seg":  # the spherical models alone
        assert "planar_unet" in seen.pop("models")
        assert main(["train", "seg", "--out", str(tmp_path), "--no-planar"]) == 0
        assert seen.pop("models") == ("spherical_unet", "spherical_deeplab")


def test_train_det_and_seg_refuse_the_options_of_train_mnist(capsys):
    for argv, said in ((["det", "--level", "3"], "--level: an option of 'train mnist', not of 'train det'"),
                       (["seg", "--source", "idx", "--pairs", "0"],
                        "--source, --pairs: options of 'train mnist', not of 'train seg'"),
                       (["seg", "--input-level", "4", "--min-level", "1", "--pair-stages", "1"],
                        "--input-level, --min-level, --pair-stages: options of 'train mnist'"),
                       (["seg", "--no-planar", "--models", "planar_unet"],
                        "--no-planar and --models planar_unet: give one of them")):
        assert main(["train", *argv]) == 2
        assert said in capsys.readouterr().err


def test_train_mnist_refuses_the_options_of_train_det_and_seg(capsys):
    for argv, named in ((["--channel-scale", "0.5"], "--channel-scale"),
                        (["--materials", "by_kind", "--up-sign", "0"], "--materials, --up-sign"),
                        (["--dataset", "pandora", "--fold", "2"], "--dataset, --fold"),
                        (["--gray"], "--gray")):
        assert main(["train", "mnist", *argv]) == 2
        what = "options" if "," in named else "an option"
        assert f"{named}: {what} of 'train det|seg', not of 'train mnist'" in capsys.readouterr().err


def test_eval_and_train_read_each_stanford_fold(capsys):
    p = build_parser()
    assert [p.parse_args(["eval", "seg", "m.pt", "--fold", f]).fold for f in "123"] == [1, 2, 3]
    assert [p.parse_args(["train", "seg", "--fold", f]).fold for f in ("1", "2", "3", "all")] == \
        ["1", "2", "3", "all"]  # training may take the three in turn
    for cmd in (["eval", "seg", "m.pt"], ["train", "seg"]):
        with pytest.raises(SystemExit):
            p.parse_args([*cmd, "--fold", "4"])
        assert re.search(r"--fold: invalid choice: '?4'?", capsys.readouterr().err)


def test_eval_mnist_refuses_the_options_of_eval_det_and_seg(tmp_path, capsys):
    for argv, named in ((["--test", "a"], "--test"), (["--known-up", "--fold", "2"], "--fold, --known-up"),
                        (["--gray"], "--gray")):
        assert main(["eval", "mnist", str(tmp_path / "m.pt"), *argv]) == 2
        what = "options" if "," in named else "an option"
        assert f"{named}: {what} of 'eval det|seg', not of 'eval mnist'" in capsys.readouterr().err
    for task, argv, said in (("seg", ["--rotate", "none"], "--rotate: an option of 'eval mnist', not of 'eval seg'"),
                             ("det", ["--source", "idx", "--rotate", "so3"],
                              "--rotate, --source: options of 'eval mnist', not of 'eval det'")):
        assert main(["eval", task, str(tmp_path / "m.pt"), *argv]) == 2
        assert said in capsys.readouterr().err


@pytest.mark.parametrize("task", ["seg", "det", "mnist"])
def test_a_device_the_machine_lacks_is_refused_before_any_work(tmp_path, capsys, monkeypatch, task):
    monkeypatch.setattr("torch.cuda.is_available", lambda: False)
    root, out = tmp_path / "data", tmp_path / "run"
    rc = main(["train", task, "--device", "cuda", "--root", str(root), "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and "sees no CUDA GPU" in err and "--device cpu" in err
    assert not root.exists() and not out.exists()  # nothing rendered or written
    assert main(["train", task, "--device", "tpu", "--root", str(root)]) == 2
    assert "unknown device 'tpu'" in capsys.readouterr().err


def test_eval_refuses_a_device_the_machine_lacks(tmp_path, capsys, monkeypatch):
    from usf_graph.models import SphericalClassifier
    from usf_graph.train import save_checkpoint

    monkeypatch.setattr("torch.cuda.is_available", lambda: False)
    net = SphericalClassifier(level=2, input_level=2, min_level=1, pairs=0)
    save_checkpoint(tmp_path / "m.pt", net, net.config, {})
    assert main(["eval", "mnist", str(tmp_path / "m.pt"), "--device", "cuda",
                 "--root", str(tmp_path / "data")]) == 2
    assert "sees no CUDA GPU" in capsys.readouterr().err
    assert not (tmp_path / "data").exists()


def test_predict_up_lines_reads_the_images_straight_lines(tmp_path, capsys):
    """``--up-lines``: the up estimate picks among the Manhattan axes of the image's lines;
    the up printed and written is that axis, through a pinhole and through a fisheye.
    Refused with --up; a featureless image falls back to the estimate and says so."""
    import json

    from usf_graph.cameras import Fisheye, Pinhole
    from usf_graph.frontend.lines import line_normals, manhattan_axes
    from usf_graph.models import SphericalDetector
    from usf_graph.scenes import make_room, render
    from usf_graph.train import save_checkpoint
    from usf_graph.train.apply import detect_image

    cam = Pinhole(64.0, 64.0, 63.5, 63.5, 128, 128)
    scene = make_room(seed=3, index=3, materials="by_kind")
    rgb = render(scene, cam, *scene.viewpoint(0), boxes=False).rgb
    cv2.imwrite(str(tmp_path / "view.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    cam.save(tmp_path / "pinhole.yaml")
    torch.manual_seed(0)
    det = SphericalDetector(12, input_level=3, head_level=2, min_level=1, channels=(8, 8, 8), gravity=True)
    save_checkpoint(tmp_path / "det.pt", det, det.config, {})
    common = [str(tmp_path / "det.pt"), str(tmp_path / "view.png"), "--out", str(tmp_path / "out")]
    assert main(["predict", "det", *common, "--camera", str(tmp_path / "pinhole.yaml"), "--up-lines"]) == 0
    assert "picked by the estimate among the image's straight-line axes" in capsys.readouterr().out
    up = np.array(json.loads((tmp_path / "out" / "view_boxes.json").read_text())["up"]["up"])
    axes = manhattan_axes(*line_normals(rgb, cam))
    assert np.isclose(np.abs(axes @ up).max(), 1.0, atol=1e-6)  # one of the axes, either sign
    assert np.allclose(detect_image(det.eval(), rgb, cam, up="lines")["up"], up, atol=1e-6)
    flat = np.full_like(rgb, 128)
    r = detect_image(det, flat, cam, up="lines")
    assert r["source"] == "estimated" and r["lines"].startswith("too few straight lines")
    assert main(["predict", "det", *common, "--camera", str(tmp_path / "pinhole.yaml"), "--up-lines",
                 "--up", "0", "0", "1"]) == 2
    assert "not with --up" in capsys.readouterr().err
    fish = Fisheye(40.0, 63.5, 63.5, 128, 128)  # a lens that bends lines: read through pinholes
    fish_rgb = render(scene, fish, *scene.viewpoint(0), boxes=False).rgb
    cv2.imwrite(str(tmp_path / "view.png"), cv2.cvtColor(fish_rgb, cv2.COLOR_RGB2BGR))
    fish.save(tmp_path / "fish.yaml")
    assert main(["predict", "det", *common, "--camera", str(tmp_path / "fish.yaml"), "--up-lines"]) == 0
    assert "picked by the estimate among the image's straight-line axes" in capsys.readouterr().out
    up = np.array(json.loads((tmp_path / "out" / "view_boxes.json").read_text())["up"]["up"])
    axes = manhattan_axes(*line_normals(fish_rgb, fish))
    assert np.isclose(np.abs(axes @ up).max(), 1.0, atol=1e-6)
    with pytest.raises(ValueError, match="or 'lines'"):
        detect_image(det, rgb, cam, up="level")


def test_export_cli_writes_a_checked_program_from_a_camera_file(tmp_path, capsys, monkeypatch):
    """``export seg``: a checkpoint and a calibration file in, an ONNX program out that
    gives ``segment_image``'s labels; its refusals exit 2 with the fix."""
    import json

    pytest.importorskip("onnxruntime")
    from usf_graph.cameras import KannalaBrandt
    from usf_graph.models import SphericalUNet
    from usf_graph.train import save_checkpoint
    from usf_graph.train.apply import UNSEEN, segment_image
    from usf_graph.train.export import load_exported

    cam = KannalaBrandt(12.0, 12.0, 15.5, 15.5, 32, 32, k=(0.01, 0.0, 0.0, 0.0))
    cam.save(tmp_path / "fish.yaml")
    torch.manual_seed(0)
    seg = SphericalUNet(13, level=3, channels=(8, 8), gravity=True, pairs=0)
    save_checkpoint(tmp_path / "seg.pt", seg, {"model": "spherical_unet", "size": 32, **seg.config}, {})
    out = tmp_path / "seg.onnx"
    args = ["export", "seg", str(tmp_path / "seg.pt"), "--camera", str(tmp_path / "fish.yaml")]
    assert main([*args, "--fov", "180", "--up-input", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "100.00% of" in printed and "up float32 [3]" in printed
    assert f"examples/deploy_onnx.py {out} FRAME.png --up X Y Z" in printed
    info = json.loads(printed.strip().splitlines()[-1])
    assert info["format"] == "ONNX" and info["inputs"] == ["image uint8 [32, 32, 3] RGB", "up float32 [3]"]
    image = np.random.default_rng(0).integers(0, 256, (32, 32, 3), dtype=np.uint8)
    labels, _ = load_exported(out)(image, [0.0, 0.0, 1.0])
    ref = segment_image(seg.eval(), image, cam.with_fov(180), up=[0.0, 0.0, 1.0])["labels"]
    seen = ref != UNSEEN
    assert np.array_equal(labels == UNSEEN, ~seen) and (labels[seen] == ref[seen]).mean() > 0.99
    rig = ["export", "seg", str(tmp_path / "seg.pt"), "--camera", str(FIXTURES / "kalibr_rig.yaml"),
           "--rig", "--fov", "190", "--up", "0", "0", "1", "--out", str(tmp_path / "rig.onnx")]
    assert main(rig) == 0  # two back-to-back fisheyes: an image and a label image each
    assert "outputs: labels_cam0, labels_cam1 uint8" in capsys.readouterr().out
    assert main([*rig, "--key", "cam1"]) == 2 and "picks a rig in a COLMAP model; this file holds one rig" in capsys.readouterr().err
    from usf_graph.models import SignCheck

    check = SignCheck(level=3, channels=(4, 4))
    save_checkpoint(tmp_path / "sign.pt", check, {"model": "sign_check", **check.config}, {})
    signed = ["--sign-check", str(tmp_path / "sign.pt"), "--out", str(tmp_path / "signed.pt2")]
    seen = []  # the check reaches the exported model (its export: tests/train/test_export.py)

    def export(model, camera, path, up, **kw):
        seen.append((model.gravity.sign_check, up))
        return {"path": str(path), "format": "torch.export", "bytes": 0, "export_s": 0.0,
                "inputs": ["image uint8 [32, 32, 3] RGB"], "outputs": ["labels", "up_read"]}

    monkeypatch.setattr("usf_graph.train.export.export_model", export)
    assert main([*args, "--fov", "180", *signed]) == 0  # the estimate and its check inside
    [(got, up)] = seen
    assert up is None and isinstance(got, SignCheck) and not got.training
    for k, v in check.state_dict().items():
        assert torch.equal(got.state_dict()[k], v), k
    monkeypatch.undo()  # export_model's own refusals follow
    for bad, why in ((["--up", "0", "0", "1", "--level-prior", "10", "--out", str(tmp_path / "a.pt2")],
                      "--level-prior shapes"),
                     (["--up-input", *signed], "--sign-check corrects"),
                     (["--up-input", "--out", str(tmp_path / "a.onnx.txt")], ".onnx")):
        assert main([*args, *bad]) == 2
        assert why in capsys.readouterr().err


def test_export_cli_prints_what_it_wrote(tmp_path, capsys, monkeypatch):
    """``export``'s report, read from ``export_model``'s answer: size in MB, the outputs
    (a rig's label images, then the up read), the check's time a frame in ms; the ONNX
    runner's command only for one camera's ONNX file."""
    tiny_seg_checkpoint(tmp_path / "seg.pt")
    answer = {"path": "x", "format": "ONNX", "bytes": 2_345_678, "export_s": 3.25,
              "inputs": ["image_cam0 uint8", "image_cam1 uint8"],
              "outputs": ["labels_cam0", "labels_cam1", "up_read"],
              "check": {"agree": 0.98765, "pixels_seen": 1024, "up_angle_deg": 0.0123,
                        "frame_s": 0.04948, "load_s": 1.25}}
    monkeypatch.setattr("usf_graph.train.export.export_model", lambda *a, **k: answer)
    args = ["export", "seg", str(tmp_path / "seg.pt"), "--fov", "190", "--out", str(tmp_path / "x.onnx")]
    assert main([*args, "--rig", "--camera", str(FIXTURES / "kalibr_rig.yaml")]) == 0
    out = capsys.readouterr().out
    lines = out[out.index("wrote x"):].splitlines()  # after the checkpoint's provenance
    assert lines[:3] == [
        "wrote x (ONNX, 2.3 MB) in 3.2 s",
        "inputs: image_cam0 uint8, image_cam1 uint8; outputs: labels_cam0, labels_cam1 uint8 "
        "[H, W] (255: unseen), up_read float32 [3]",
        "check on a room rendered through the camera: 98.77% of 1024 pixels agree with usf-graph, "
        "ups 0.012 deg apart; 49 ms a frame here (loaded in 1.2 s)"]
    assert len(lines) == 4 and lines[3].startswith('{"path": "x", "format": "ONNX", "bytes": 2345678,')
    assert main([*args, "--camera", "equirectangular:64x32"]) == 0
    assert "python examples/deploy_onnx.py x FRAME.png\n" in capsys.readouterr().out
    for bad, why in ((args, "the following arguments are required: --camera"),
                     ([*args, "--camera", "equirectangular:64x32", "--split"], "unrecognized arguments: --split")):
        with pytest.raises(SystemExit):
            main(bad)
        assert why in capsys.readouterr().err


def test_export_det_decodes_by_default_as_predict_and_eval_do(tmp_path, capsys):
    from usf_graph.cli_export import DECODING
    from usf_graph.train.apply import detect_image
    from usf_graph.train.engine import defaults

    d = defaults(detect_image)
    assert DECODING == {"max_boxes": d["k"], "threshold": d["threshold"], "nms": d["nms"]}
    (tmp_path / "seg.pt").write_bytes(b"")  # refused before it is read
    assert main(["export", "seg", str(tmp_path / "seg.pt"), "--camera", "equirectangular:64x32",
                 "--nms", "0.3", "--out", str(tmp_path / "seg.onnx")]) == 2
    assert "--nms: a detector's decoding" in capsys.readouterr().err
    assert main(["export", "seg", str(tmp_path / "seg.pt"), "--camera", "equirectangular:64x32",
                 "--out", str(tmp_path / "seg.tflite")]) == 2
    assert "seg.tflite: name the file .onnx (ONNX) or .pt2" in capsys.readouterr().err


def test_export_cli_writes_a_detector_with_its_decoding(tmp_path, capsys):
    """``export det``: the decoding options reach the program, which gives
    ``detect_image``'s boxes with the same options; a segmentation checkpoint is refused."""
    import json

    pytest.importorskip("onnxruntime")
    from usf_graph.cameras import KannalaBrandt
    from usf_graph.models import SphericalDetector, SphericalUNet
    from usf_graph.train import save_checkpoint
    from usf_graph.train.apply import detect_image
    from usf_graph.train.export import load_exported

    cam = KannalaBrandt(12.0, 12.0, 15.5, 15.5, 32, 32, k=(0.01, 0.0, 0.0, 0.0))
    cam.save(tmp_path / "fish.yaml")
    torch.manual_seed(0)
    det = SphericalDetector(num_classes=12, input_level=3, head_level=2, min_level=1,
                            channels=(4, 6, 8), pairs=2, gradient_fields=2, gravity=True)
    with torch.no_grad():  # heatmaps that peak above the threshold here and there
        det.head.weight[:12].mul_(30.0)
        det.head.bias[:12].fill_(-1.0)
    save_checkpoint(tmp_path / "det.pt", det, {"size": 32, **det.config}, {})
    out = tmp_path / "det.onnx"
    args = ["export", "det", str(tmp_path / "det.pt"), "--camera", str(tmp_path / "fish.yaml"),
            "--fov", "180", "--up", "0", "0", "1"]
    assert main([*args, "--max-boxes", "30", "--threshold", "0.1", "--nms", "1", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "boxes float32 [30, 5] (radians)" in printed and "detections found alike" in printed
    run = load_exported(out)
    assert json.loads(run.metadata["decoding"]) == {"k": 30, "threshold": 0.1, "nms": None,
                                                    "drop_hidden": True}
    image = np.random.default_rng(0).integers(0, 256, (32, 32, 3), dtype=np.uint8)
    got, _ = run(image)
    want = detect_image(det.eval(), image, cam.with_fov(180), up=[0.0, 0.0, 1.0], k=30,
                        threshold=0.1, nms=None)
    assert len(got["boxes"]) == len(want["boxes"]) > 0
    assert np.array_equal(got["classes"], want["classes"])
    np.testing.assert_allclose(got["scores"], want["scores"], atol=1e-5)
    torch.manual_seed(0)
    seg = SphericalUNet(13, level=3, channels=(8, 8), pairs=0)
    save_checkpoint(tmp_path / "seg.pt", seg, {"model": "spherical_unet", "size": 32, **seg.config}, {})
    args[2] = str(tmp_path / "seg.pt")
    assert main([*args, "--out", str(out)]) == 2
    assert "not a spherical det model" in capsys.readouterr().err


def test_lift_and_predict_choose_the_stitching_distance(tmp_path, capsys):
    """``--distance auto``: the rig's images of a sphere 1.5 m away (trimesh-cast from each
    camera) are stitched at 1.5 m, the candidate where the seams agree."""
    from tests.frontend.test_rig import ball_shots

    chain = FIXTURES / "kalibr_rig.yaml"
    rig = {n: c.with_fov(190) for n, c in cameras.load_rig(chain).items()}
    _, shots = ball_shots(rig, 1.5)
    paths = []
    for name, im in zip(rig, shots):
        paths.append(str(tmp_path / f"{name}.png"))
        cv2.imwrite(paths[-1], (255 * im[..., ::-1]).round().astype(np.uint8))
    assert main(["lift", *paths, "--camera", str(chain), "--fov", "190", "--grid", "icosahedral:4",
                 "--distance", "auto", "--out", str(tmp_path / "r.pt")]) == 0
    assert "chosen where the cameras agree best: 1.41 (" in capsys.readouterr().out
    assert read_lifted(tmp_path / "r.pt")["cameras"]["cam0"]["distance"] == pytest.approx(1.414, abs=1e-3)
    tiny_seg_checkpoint(tmp_path / "seg.pt")
    assert main(["predict", "seg", str(tmp_path / "seg.pt"), *paths, "--rig", "--camera", str(chain),
                 "--fov", "190", "--distance", "auto", "--out", str(tmp_path / "out")]) == 0
    assert "chosen where the cameras agree best: 1.41 (" in capsys.readouterr().out
    assert main(["export", "seg", str(tmp_path / "seg.pt"), "--rig", "--camera", str(chain),
                 "--distance", "auto", "--out", str(tmp_path / "x.pt2")]) == 2
    assert "--distance auto chooses from the rig's images" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["lift", *paths, "--camera", str(chain), "--distance", "far"])
    assert "a distance in the calibration's unit, or 'auto'" in capsys.readouterr().err


@pytest.mark.parametrize("task", ["seg", "det"])
def test_eval_scores_a_checkpoint_through_the_users_camera(task, tmp_path, capsys):
    """``eval --camera``: (a) and the rooms through that camera, zero-shot; the camera's
    score is what the same test views, rendered through it by hand, give."""
    from usf_graph.datasets import RoomsDetection, RoomsSegmentation
    from usf_graph.models import SphericalDetector
    from usf_graph.train import det, save_checkpoint, seg_eval
    from usf_graph.train.apply import choose_interpolation

    cam = cameras.KannalaBrandt(20.0, 20.0, 31.5, 23.5, 64, 48, k=(0.01, 0.0, 0.0, 0.0))
    cam.save(tmp_path / "fisheye.yaml")
    data = {"dataset": "rooms", "seed": 0, "materials": "random"}
    if task == "seg":
        net = tiny_seg_checkpoint(tmp_path / "m.pt", size=16)
        save_checkpoint(tmp_path / "m.pt", net, {"model": "spherical_unet", "size": 16,
                                                 **net.config}, {}, extra={"data": data})
    else:
        torch.manual_seed(0)
        net = SphericalDetector(12, input_level=3, head_level=2, min_level=1, channels=(4, 4, 4))
        save_checkpoint(tmp_path / "m.pt", net, {"size": 16, **net.config}, {},
                        extra={"data": data})
    root = tmp_path / "rooms"
    assert main(["eval", task, str(tmp_path / "m.pt"), "--root", str(root), "--num-test", "2",
                 "--camera", str(tmp_path / "fisheye.yaml"), "--figure",
                 str(tmp_path / "fig.png")]) == 0
    out = capsys.readouterr().out
    assert f"figure: {tmp_path / 'fig.png'}" in out
    fig = cv2.imread(str(tmp_path / "fig.png"))
    # seg: a row per test (a, camera) of image, truth, prediction; det: one row of two
    assert fig.shape[0] > (2 if task == "seg" else 1) * 48 and fig.shape[1] > 2 * 64
    lines = [ln for ln in out.splitlines() if ln.startswith("(")]
    assert [ln.split()[0] for ln in lines if "mIoU" in ln or "AP50" in ln] == ["(a)", "(camera)"]
    grid = "icosahedral:3"
    kw = dict(camera=cameras.load(tmp_path / "fisheye.yaml"), grid=grid, rotate="none",
              num_scenes=2, seed=0, materials="random", progress=False,
              interpolation=choose_interpolation(cam, grids.from_spec(grid)))
    net.eval()
    if task == "seg":
        r = seg_eval.evaluate_set(net, RoomsSegmentation(root, "test", **kw), progress=False)[0]
        want = f"(camera) mIoU {100 * r['mIoU']:.2f}, mAcc {100 * r['mAcc']:.2f}"
    else:
        data = det.DetectionSet.spherical(RoomsDetection(root, "test", **kw))
        r = det.score(det.predict(net, data, det.PREDICT_BATCH), data, net.num_classes)
        want = f"(camera) AP {100 * r['AP']:.2f}, AP50 {100 * r['AP50']:.2f}"
    assert any(ln.startswith(want) for ln in lines), (want, lines)
