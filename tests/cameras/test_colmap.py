"""COLMAP's camera lists, checked against pycolmap (COLMAP's own camera models)."""

import struct
import sys

import numpy as np
import pycolmap
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.fixtures.make_colmap_fixture import CAMERAS, H, W
from tests.helpers import FIXTURES
from usf_graph import cameras as C
from usf_graph.cameras.colmap import CLOSED_FORM, HALF_PIXEL, colmap_entry, save_text
from usf_graph.cli import main

FOLDERS = {"text": FIXTURES / "colmap", "binary": FIXTURES / "colmap_bin"}
IDS = {model: i for i, model in enumerate(CAMERAS, 1)}
TYPES = {"EUCM": C.EUCM, "EQUIRECTANGULAR": C.Equirectangular, "FOV": C.FOV,
         "DIVISION": C.Division, "SIMPLE_DIVISION": C.Division}


def reference(model: str):
    cam = pycolmap.Camera.create_from_model_name(IDS[model], model, 1.0, W, H)
    cam.params = CAMERAS[model]
    return cam


def both_ways(ref, n: int = 3000, seed: int = 0):
    """COLMAP pixels (its convention) and their rays, where pycolmap maps both ways (its
    fisheyes end at 90 degrees: past that its ray is mirrored)."""
    uv = np.random.default_rng(seed).uniform([0, 0], [W, H], (n, 2))
    rays = np.asarray(ref.cam_ray_from_img(uv), np.float64)
    ok = np.all(np.isfinite(rays), -1)
    ok[ok] = np.linalg.norm(np.asarray(ref.img_from_cam(rays[ok])) - uv[ok], axis=-1) < 1e-6
    return uv[ok], rays[ok] / np.linalg.norm(rays[ok], axis=-1, keepdims=True)


@pytest.mark.parametrize("form", sorted(FOLDERS))
@pytest.mark.parametrize("model", CLOSED_FORM)
def test_closed_form_models_match_pycolmap(form, model):
    cam = C.load(FOLDERS[form], key=IDS[model])
    kind = C.KannalaBrandt if "FISHEYE" in model else C.Pinhole
    assert type(cam) is TYPES.get(model, kind)
    uv, rays = both_ways(reference(model))
    assert len(uv) > 2000
    sphere = rays @ C.DEFAULT_ROTATION.T  # COLMAP's camera frame is OpenCV's
    px, seen = cam.sees(sphere)
    assert seen.all()
    np.testing.assert_allclose(px + HALF_PIXEL, uv, atol=1e-6, rtol=0)
    back, valid = cam.unproject(uv - HALF_PIXEL)
    assert valid.all()
    err = np.arccos(np.clip(np.sum((back @ cam.rotation.T) * sphere, -1), -1, 1))
    assert err.max() < 1e-7


@pytest.mark.parametrize("model", ["THIN_PRISM_FISHEYE", "RAD_TAN_THIN_PRISM_FISHEYE"])
def test_other_models_become_pycolmaps_ray_table(model):
    cam = C.load(FOLDERS["binary"], key=IDS[model])
    assert isinstance(cam, C.LensNormalMap) and f"COLMAP {model}" in cam.source
    ref = reference(model)
    uv, rays = both_ways(ref)
    px, seen = cam.sees(rays @ C.DEFAULT_ROTATION.T)
    assert seen.mean() > 0.95  # all but the cells that touch the table's edge of validity
    # bilinear between pixel centres, 1.4-2.9 degrees apart on these tiny images
    assert np.abs(px[seen] + HALF_PIXEL - uv[seen]).max() < 2e-2
    lnm, valid = cam.lens_normal_map()
    grid = np.stack(np.meshgrid(np.arange(W), np.arange(H)), -1).reshape(-1, 2) + HALF_PIXEL
    want = np.asarray(ref.cam_ray_from_img(grid), np.float64).reshape(H, W, 3)
    want = want / np.linalg.norm(want, axis=-1, keepdims=True) @ C.DEFAULT_ROTATION.T
    np.testing.assert_allclose(lnm[valid], want[valid], atol=1e-12)
    if "THIN_PRISM" in model:  # past 90 degrees COLMAP's ray is mirrored: dropped
        assert 0.5 < valid.mean() < 0.98 and cam.fov_deg <= 180.0 + 1e-6


def test_text_and_binary_lists_read_alike_and_the_principal_point_moves_half_a_pixel():
    for model, i in IDS.items():
        a, b = (C.load(FOLDERS[f], key=i) for f in ("text", "binary"))
        strip = (lambda k: {**k, "params": {**k["params"], "source": None}}) \
            if "THIN_PRISM" in model else (lambda k: k)
        assert type(a) is type(b) and strip(a.key()) == strip(b.key()), model
    cam = C.load(FOLDERS["text"], key="2")  # PINHOLE 40 41 32.3 24.7; a string id works too
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (40.0, 41.0, 32.3 - 0.5, 24.7 - 0.5)
    np.testing.assert_allclose(cam.project(np.array([0.0, 0.0, 1.0]))[0], [31.8, 24.2])
    assert C.load(FOLDERS["text"] / "cameras.txt", key=7).k[3] == -0.0005


def test_keys_and_bad_files_get_clear_errors(tmp_path):
    with pytest.raises(ValueError, match=r"18 COLMAP cameras \(ids 1, 2, .*--key"):
        C.load(FOLDERS["text"])
    with pytest.raises(ValueError, match=r"no COLMAP camera '99'"):
        C.load(FOLDERS["text"], key="99")
    with pytest.raises(ValueError, match=r"no COLMAP camera 'cam0'"):
        C.load(FOLDERS["binary"], key="cam0")
    one = tmp_path / "cameras.txt"
    one.write_text("# Camera list with one line of data per camera:\n1 PINHOLE 64 48 40 40 32 24\n")
    assert C.load(one).cx == 31.5 and C.load(tmp_path).cx == 31.5  # one camera: no key needed
    with pytest.raises(ValueError, match="Kalibr camchain"):
        C.load_rig(one)
    bad = {"line 2: COLMAP's OPENCV has 8 parameters, got 4": "1 PINHOLE 64 48 40 40 32 24\n"
           "2 OPENCV 64 48 40 40 32 24\n",
           "unknown COLMAP camera model 'KB4'": "# Camera list\n1 KB4 64 48 40 40 32 24\n",
           "camera id 1 appears twice": "1 PINHOLE 64 48 40 40 32 24\n1 PINHOLE 64 48 40 40 32 24\n",
           "must be numbers": "# Camera list\n1 PINHOLE 64 x 40 40 32 24\n",
           "EQUIRECTANGULAR's parameters .* must equal its image size": "1 EQUIRECTANGULAR 64 32 64 48\n",
           "fx must be": "1 PINHOLE 64 48 -40 40 32 24\n"}
    for why, text in bad.items():
        one.write_text(text)
        with pytest.raises(ValueError, match=why):
            C.load(one, key=1)
    data = (FOLDERS["binary"] / "cameras.bin").read_bytes()
    cut = tmp_path / "cut" / "cameras.bin"
    cut.parent.mkdir()
    cut.write_bytes(data[:-8])
    with pytest.raises(ValueError, match="not COLMAP's cameras.bin"):
        C.load(cut.parent, key=1)
    cut.write_bytes(struct.pack("<QIiQQ", 1, 1, 99, 64, 48))  # model id 99
    with pytest.raises(ValueError, match="not COLMAP's cameras.bin"):
        C.load(cut, key=1)
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="without cameras.bin or cameras.txt"):
        C.load(tmp_path / "empty")


def test_ray_table_models_without_pycolmap_say_how_to_read_them(monkeypatch):
    monkeypatch.setitem(sys.modules, "pycolmap", None)
    with pytest.raises(ValueError, match=r"COLMAP's THIN_PRISM_FISHEYE has no closed form.*pip install pycolmap"):
        C.load(FOLDERS["text"], key=IDS["THIN_PRISM_FISHEYE"])
    assert isinstance(C.load(FOLDERS["text"], key=IDS["OPENCV_FISHEYE"]), C.KannalaBrandt)


def test_cli_reads_a_sparse_model(capsys):
    assert main(["camera", str(FOLDERS["binary"]), "--key", str(IDS["OPENCV_FISHEYE"])]) == 0
    assert "kannala-brandt" in capsys.readouterr().out.lower()
    assert main(["camera", str(FOLDERS["binary"])]) == 2
    assert "--key" in capsys.readouterr().err


def test_load_all_lists_every_camera_by_the_key_that_picks_it(capsys):
    everything = C.load_all(FOLDERS["text"])
    assert list(everything) == list(range(1, 19))
    assert everything[7].key() == C.load(FOLDERS["text"], key=7).key()
    rig = C.load_all(FIXTURES / "kalibr_rig.yaml")
    assert list(rig) == ["cam0", "cam1"] and rig["cam1"].key() == C.load_rig(FIXTURES / "kalibr_rig.yaml")["cam1"].key()
    one = C.load_all(FIXTURES / "opencv_pinhole.yaml")
    assert list(one) == [None] and one[None].key() == C.load(FIXTURES / "opencv_pinhole.yaml").key()
    assert main(["camera", str(FOLDERS["binary"]), "--all"]) == 0
    rows = capsys.readouterr().out.splitlines()
    assert len(rows) == 19 and rows[7].split()[:3] == ["7", "kannala-brandt", "64x48"]
    assert main(["camera", str(FOLDERS["binary"]), "--all", "--key", "2"]) == 2
    assert "leave out --key" in capsys.readouterr().err


WRITABLE = {
    1: C.Pinhole(300, 310, 320.2, 240.7, 640, 480),
    2: C.Pinhole(300, 310, 320.2, 240.7, 640, 480, dist=(0.1, -0.05, 0.001, 0.002)),
    3: C.Pinhole(300, 310, 320.2, 240.7, 640, 480, dist=(0.1, -0.05, 0.001, 0.002, 0.01, 0.02, 0.001, 0.0005)),
    4: C.KannalaBrandt(200, 205, 320.2, 240.7, 640, 480, k=(0.01, 0.002, -0.001, 0.0001)),
    5: C.Fisheye(200, 320.2, 240.7, 640, 480, model="equidistant"),
    6: C.EUCM(250, 255, 320.2, 240.7, 640, 480, alpha=0.6, beta=1.1),
    7: C.Mei(500, 505, 320.2, 240.7, 640, 480, xi=1.2),  # undistorted Mei: COLMAP's EUCM
    8: C.Equirectangular(640, 320),
    9: C.FOV(300, 305, 320.2, 240.7, 640, 480, omega=0.9),
    10: C.Division(300, 305, 320.2, 240.7, 640, 480, k=-0.3),
    11: C.Division(300, 305, 320.2, 240.7, 640, 480, k=0.2),
}


def test_cameras_written_for_colmap_project_as_pycolmap_reads_them(tmp_path):
    save_text(WRITABLE, tmp_path / "cameras.txt")
    for name in ("images.txt", "points3D.txt"):  # pycolmap reads a whole sparse model
        (tmp_path / name).write_text("")
    rec = pycolmap.Reconstruction()
    rec.read_text(str(tmp_path))
    assert sorted(rec.cameras) == sorted(WRITABLE)
    rays = np.random.default_rng(1).normal(size=(4000, 3)) + [0, 0, 1.2]
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    for cid, cam in WRITABLE.items():
        sphere = rays @ C.DEFAULT_ROTATION.T
        ours, seen = cam.sees(sphere)
        theirs = np.asarray(rec.cameras[cid].img_from_cam(rays), np.float64)
        both = seen & np.all(np.isfinite(theirs), -1)
        assert both.mean() > 0.3, cid
        np.testing.assert_allclose(ours[both] + HALF_PIXEL, theirs[both], atol=1e-6, rtol=0,
                                   err_msg=f"camera {cid}")
        back = C.load(tmp_path, key=cid)  # and our reader takes it back
        np.testing.assert_allclose(back.sees(sphere)[0][seen], ours[seen], atol=1e-9)


def test_cameras_colmap_cannot_hold_are_refused_and_nothing_is_written(tmp_path, capsys):
    out = tmp_path / "cameras.txt"
    for bad in (C.DoubleSphere(300, 300, 320, 240, 640, 480, xi=-0.2, alpha=0.6),
                C.Mei(500, 500, 320, 240, 640, 480, xi=1.2, dist=(0.1, 0, 0, 0)),
                C.Pinhole(300, 300, 320, 240, 640, 480, dist=[0.1, 0, 0, 0, 0, 0, 0, 0, 0.01, 0, 0, 0]),
                C.Equirectangular(640, 160, lat_range=(0.0, 1.5))):
        with pytest.raises(ValueError, match=r"camera 2: COLMAP has no model for this"):
            save_text({1: WRITABLE[1], 2: bad}, out)
        assert not out.exists()
    assert main(["camera", str(FIXTURES / "kalibr_rig.yaml"), "--all", "--save-colmap", str(out)]) == 0
    out_text = capsys.readouterr().out
    assert "(COLMAP's camera list, 2 cameras;" in out_text and "not in COLMAP's list" in out_text
    assert list(C.load_all(out)) == [1, 2] and isinstance(C.load(out, key=2), C.KannalaBrandt)


@settings(max_examples=40, deadline=None)
@given(f=st.tuples(st.floats(50, 2000), st.floats(50, 2000)), c=st.tuples(st.floats(0, 640), st.floats(0, 480)),
       d=st.lists(st.floats(-0.05, 0.05), min_size=8, max_size=8), kind=st.sampled_from(["OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE", "EUCM"]),
       binary=st.booleans())
def test_colmap_parameters_survive_a_write_and_a_read_to_the_bit(tmp_path_factory, f, c, d, kind, binary):
    """Any calibration written (text) and read back, as text or after pycolmap rewrote it
    as binary, has the same parameters to the last bit; the principal point to the
    rounding of the half pixel added and taken away."""
    K = dict(fx=f[0], fy=f[1], cx=c[0], cy=c[1], width=640, height=480)
    cam = {"OPENCV": lambda: C.Pinhole(**K, dist=d[:4]),
           "FULL_OPENCV": lambda: C.Pinhole(**K, dist=d[:4] + [0.0] * 3 + [0.01]),
           "OPENCV_FISHEYE": lambda: C.KannalaBrandt(**K, k=[abs(v) / 10 for v in d[:4]]),
           "EUCM": lambda: C.EUCM(**K, alpha=abs(d[0]) * 10, beta=1 + d[1])}[kind]()
    folder = tmp_path_factory.mktemp("colmap")
    save_text({3: cam}, folder / "cameras.txt")
    if binary:
        for name in ("images.txt", "points3D.txt"):
            (folder / name).write_text("")
        rec = pycolmap.Reconstruction()
        rec.read_text(str(folder))
        (folder / "cameras.txt").unlink()
        rec.write_binary(str(folder))
        assert rec.cameras[3].model_name == colmap_entry(cam)[0]
    back = C.load(folder, key=3)
    assert type(back) is type(cam)
    want, got = cam.params(), back.params()
    if isinstance(cam, C.Pinhole):  # no distortion is written as PINHOLE: dist None, same camera
        want["dist"], got["dist"] = cam.dist.tolist(), back.dist.tolist()
    for name in ("cx", "cy"):  # moved half a pixel and back: a rounding of the sum at most
        assert got.pop(name) == pytest.approx(want.pop(name), rel=0, abs=1e-12)
    assert got == want


@pytest.mark.parametrize("where", ["colmap_rig", "colmap_rig_bin", "colmap_rig/rigs.txt"])
def test_a_colmap_rig_mounts_its_cameras_by_their_poses(where):
    rig = C.load_rig(FIXTURES / where)
    assert list(rig) == ["1", "2", "3"]  # the IMU of the rig is left out
    assert all(isinstance(c, C.KannalaBrandt) and c.cx == 31.5 for c in rig.values())
    axis = {n: c.rotation @ [0.0, 0.0, 1.0] for n, c in rig.items()}
    np.testing.assert_allclose(axis["1"], [1, 0, 0], atol=1e-12)  # the reference: forward
    np.testing.assert_allclose(axis["2"], [-1, 0, 0], atol=1e-12)  # turned around
    np.testing.assert_allclose(axis["3"], [0, 1, 0], atol=1e-12)  # to the left
    np.testing.assert_allclose(rig["2"].rotation @ [0.0, 1.0, 0.0], [0, 0, -1], atol=1e-12)


def test_colmap_rigs_refuse_what_they_cannot_mount(tmp_path):
    text = (FIXTURES / "colmap_rig" / "rigs.txt").read_text()
    (tmp_path / "cameras.txt").write_text((FIXTURES / "colmap_rig" / "cameras.txt").read_text())
    line = next(ln for ln in text.splitlines() if ln.startswith("4 "))
    second = "5 2 CAMERA 1 CAMERA 3 1 1 0 0 0 0 0 0"
    (tmp_path / "rigs.txt").write_text(line + "\n" + second + "\n")
    with pytest.raises(ValueError, match=r"2 COLMAP rigs \(ids 4, 5\); choose one with key="):
        C.load_rig(tmp_path)
    assert list(C.load_rig(tmp_path, key=5)) == ["1", "3"]
    with pytest.raises(ValueError, match=r"no COLMAP rig 7"):
        C.load_rig(tmp_path, key=7)
    (tmp_path / "rigs.txt").write_text("5 2 CAMERA 1 CAMERA 3 0\n")  # no pose for camera 3
    with pytest.raises(ValueError, match=r"\[rig 5, camera 3\]: no pose in the rig"):
        C.load_rig(tmp_path)
    (tmp_path / "rigs.txt").write_text("5 2 CAMERA 1 CAMERA 3 1 1 0 0\n")  # cut short
    with pytest.raises(ValueError, match="not COLMAP's rig list"):
        C.load_rig(tmp_path)
    cut = tmp_path / "bin"
    cut.mkdir()
    data = (FIXTURES / "colmap_rig_bin" / "rigs.bin").read_bytes()
    (cut / "rigs.bin").write_bytes(data[:-3])
    with pytest.raises(ValueError, match="not COLMAP's rig list"):
        C.load_rig(cut)
    junk = tmp_path / "junk"
    junk.mkdir()
    (junk / "rigs.txt").write_text(line + "\n")
    (junk / "cameras.txt").write_text("not a camera list\n")
    with pytest.raises(ValueError, match=r"cameras.txt: not COLMAP's camera list, which the rig"):
        C.load_rig(junk)
    with pytest.raises(ValueError, match="picks a rig in a COLMAP model"):
        C.load_rig(FIXTURES / "kalibr_rig.yaml", key=1)


def test_the_cli_lifts_a_colmap_rigs_images_onto_one_sphere(tmp_path):
    import cv2

    from usf_graph.frontend import load_lifted

    names = []
    for i in range(3):
        names.append(str(tmp_path / f"cam{i}.png"))
        cv2.imwrite(names[-1], np.full((H, W, 3), 60 * (i + 1), np.uint8))
    assert main(["lift", *names, "--camera", str(FIXTURES / "colmap_rig_bin"), "--grid",
                 "icosahedral:3", "--out", str(tmp_path / "rig.pt")]) == 0
    lifted = load_lifted(tmp_path / "rig.pt")
    rig = C.load_rig(FIXTURES / "colmap_rig_bin")
    pos = lifted.pos.double().numpy()
    seen = np.stack([cam.sees(pos)[1] for cam in rig.values()])  # [3, N]
    mask = lifted.mask.numpy()
    assert mask.mean() > 0.8 and not (mask & ~seen.any(0)).any()
    # blend="best": each point takes the grey of the camera that sees it looking closest
    axes = np.stack([cam.rotation @ [0.0, 0.0, 1.0] for cam in rig.values()])
    best = np.argmax(np.where(seen, axes @ pos.T, -np.inf), 0)
    assert set(best[mask]) == {0, 1, 2}
    want = np.broadcast_to(60 * (best[mask, None] + 1.0), (int(mask.sum()), 3))
    np.testing.assert_allclose(lifted.x[mask].numpy(), want, atol=1e-4)


def test_opencvs_model_with_zero_thin_prism_terms_is_written_as_full_opencv():
    d = [0.1, -0.02, 0.001, 0.002, 0.003, 0.01, -0.004, 0.0005]
    cam = C.Pinhole(500.0, 510.0, 319.5, 239.5, 640, 480, dist=d + [0.0] * 4)  # s1..s4 zero
    assert colmap_entry(cam) == ("FULL_OPENCV", [500.0, 510.0, 320.0, 240.0] + d)


def test_a_list_of_many_cameras_names_the_first_eight_ids(tmp_path):
    rows = "".join(f"{i} PINHOLE 64 48 50 50 32 24\n" for i in range(1, 11))
    (tmp_path / "cameras.txt").write_text(rows)
    with pytest.raises(ValueError, match=r"10 COLMAP cameras \(ids 1, 2, 3, 4, 5, 6, 7, 8, \.\.\. \(10 in all\)\)"):
        C.load(tmp_path)


def test_a_ray_table_model_that_gives_no_pixel_a_ray_is_refused(tmp_path):
    (tmp_path / "cameras.txt").write_text("1 THIN_PRISM_FISHEYE 8 6 0 0 4 3 0 0 0 0 0 0 0 0\n")
    with pytest.raises(ValueError, match=r"\[camera 1\]: pycolmap gives no pixel of this THIN_PRISM_FISHEYE "
                                         r"camera a ray; check its parameters \[0\.0, 0\.0, 4\.0"):
        C.load(tmp_path)
