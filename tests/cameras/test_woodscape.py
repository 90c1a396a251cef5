"""WoodScape's radial polynomial fisheye and its calibration JSON: the projection against
the formula written out here and against ``cv2.fisheye`` where the polynomial is odd, the
inverse, resizing, the mounting against SciPy's reading of the quaternion, and the errors."""

import json
import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from tests.helpers import FIXTURES
from usf_graph import cameras
from usf_graph.cameras import RadialPoly

RV = FIXTURES / "woodscape_rv.json"


def _formula(rays, k, cx, cy, aspect):
    """WoodScape's projection from its definition: rho = sum k_i theta^i pixels along the
    ray's azimuth, the vertical scaled by the aspect ratio."""
    x, y, z = rays.T
    chi = np.hypot(x, y)
    theta = np.arctan2(chi, z)
    rho = sum(c * theta ** (i + 1) for i, c in enumerate(k))
    return np.stack([cx + rho * x / chi, cy + aspect * rho * y / chi], 1)


def _rays(n, seed, max_deg):
    rng = np.random.default_rng(seed)
    theta = np.radians(rng.uniform(0.5, max_deg, n))
    phi = rng.uniform(-np.pi, np.pi, n)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], 1)


def test_the_calibration_file_reads_as_woodscape_defines_it():
    doc = json.loads(RV.read_text())
    intr, ext = doc["intrinsic"], doc["extrinsic"]
    cam = cameras.load(RV)
    assert isinstance(cam, RadialPoly) and (cam.width, cam.height) == (1280, 966)
    assert cam.cx == pytest.approx(640 + intr["cx_offset"] - 0.5)
    assert cam.cy == pytest.approx(483 + intr["cy_offset"] - 0.5)
    rays = _rays(500, 0, 110)
    uv, ok = cam.project(rays)  # rays in the optical frame
    k = [intr[f"k{i}"] for i in range(1, 5)]
    np.testing.assert_allclose(uv, _formula(rays, k, cam.cx, cam.cy, 1.0), atol=1e-9)
    assert ok.all()
    # the optical frame into the vehicle's (x forward, y left, z up) as SciPy reads the
    # quaternion (x, y, z, w), and the translation as the position: a rear camera looking
    # back and 28 degrees down, its image's right on the car's left
    np.testing.assert_allclose(cam.rotation, Rotation.from_quat(ext["quaternion"]).as_matrix(),
                               atol=1e-12)
    np.testing.assert_allclose(cam.rotation[:, 2], [-math.cos(math.radians(28)), 0,
                                                    -math.sin(math.radians(28))], atol=1e-9)
    np.testing.assert_allclose(cam.rotation[:, 0], [0, 1, 0], atol=1e-9)
    np.testing.assert_allclose(cam.position, ext["translation"])
    assert 185 < cam.fov_deg < 240  # WoodScape's lenses see about 190 degrees across


@pytest.mark.parametrize("aspect", [1.0, 1.07])
def test_an_odd_polynomial_projects_as_cv2_fisheye(aspect):
    """With k2 = k4 = 0 the polynomial is Kannala-Brandt's: OpenCV's fisheye projection with
    f = k1 and D = (k3 / k1, 0, 0, 0), the vertical focal length times the aspect ratio."""
    k1, k3, cx, cy = 320.0, 40.0, 650.2, 470.9
    cam = RadialPoly([k1, 0.0, k3, 0.0], cx, cy, 1280, 966, aspect_ratio=aspect)
    rays = _rays(300, 1, 85)
    uv, ok = cam.project(rays)
    K = np.array([[k1, 0, cx], [0, aspect * k1, cy], [0, 0, 1]])
    ref, _ = cv2.fisheye.projectPoints(rays[None], np.zeros(3), np.zeros(3), K,
                                       np.array([k3 / k1, 0, 0, 0]))
    np.testing.assert_allclose(uv, ref[0], atol=1e-8)
    assert ok.all()


@settings(max_examples=30, deadline=None)
@given(u=st.floats(0, 1279), v=st.floats(0, 965), scale=st.sampled_from([0.5, 1.0, 1.5]))
def test_pixels_unproject_and_project_back_at_any_size(u, v, scale):
    cam = cameras.load(RV)
    if scale != 1.0:
        small = cam.resized(round(1280 * scale), round(966 * scale))
        # the same ray lands where cv2.resize moves the pixel
        ray, ok = cam.unproject(np.array([[u, v]]))
        uv, _ = small.project(ray)
        np.testing.assert_allclose(uv[0], [(u + 0.5) * scale - 0.5, (v + 0.5) * scale - 0.5],
                                   atol=1e-8)
        cam = small
        u, v = (u + 0.5) * scale - 0.5, (v + 0.5) * scale - 0.5
    ray, ok = cam.unproject(np.array([[u, v]]))
    assert ok.all() and abs(np.linalg.norm(ray) - 1) < 1e-12
    back, ok2 = cam.project(ray)
    assert ok2.all() and np.abs(back[0] - [u, v]).max() < 1e-8


def test_it_saves_and_loads_in_usf_graphs_yaml(tmp_path):
    cam = cameras.load(RV)
    cam.save(tmp_path / "rv.yaml")
    back = cameras.load(tmp_path / "rv.yaml")
    rays = _rays(50, 2, 100)
    np.testing.assert_allclose(back.project(rays)[0], cam.project(rays)[0], atol=1e-9)
    np.testing.assert_allclose(back.rotation, cam.rotation, atol=1e-12)
    np.testing.assert_allclose(back.position, cam.position)


def test_bad_calibrations_name_the_problem(tmp_path):
    doc = json.loads(RV.read_text())

    def load(change):
        d = json.loads(json.dumps(doc))
        change(d)
        (tmp_path / "c.json").write_text(json.dumps(d))
        return cameras.load(tmp_path / "c.json")

    with pytest.raises(ValueError, match="missing key 'k3' in 'intrinsic'"):
        load(lambda d: d["intrinsic"].pop("k3"))
    with pytest.raises(ValueError, match="model 'kb' is not supported"):
        load(lambda d: d["intrinsic"].update(model="kb"))
    with pytest.raises(ValueError, match="k1 > 0"):
        load(lambda d: d["intrinsic"].update(k1=-3.0))
    with pytest.raises(ValueError, match="quaternion' has norm 2"):
        load(lambda d: d["extrinsic"].update(quaternion=[2.0, 0, 0, 0]))
    with pytest.raises(ValueError, match="'k2' must be finite"):
        load(lambda d: d["intrinsic"].update(k2=float("nan")))
    with pytest.raises(ValueError, match="not increasing over the claimed fov_deg=200"):
        RadialPoly([300.0, 0, -200.0], 640, 480, 1280, 966, fov_deg=200)
    assert load(lambda d: d.pop("extrinsic")).position is None  # the intrinsics alone
    for w in (1280.5, 0):
        with pytest.raises(ValueError, match="image size must be whole positive numbers"):
            load(lambda d, w=w: d["intrinsic"].update(width=w))
    # poly_order 4 and aspect_ratio 1 where the file leaves them out; as written where given
    plain = load(lambda d: [d["intrinsic"].pop(k) for k in ("poly_order", "aspect_ratio")])
    assert list(plain.k) == [doc["intrinsic"][f"k{i}"] for i in range(1, 5)] and plain.aspect_ratio == 1.0
    given = load(lambda d: d["intrinsic"].update(poly_order=3, aspect_ratio=1.02))
    assert list(given.k) == [doc["intrinsic"][f"k{i}"] for i in range(1, 4)] and given.aspect_ratio == 1.02


def test_a_cars_four_cameras_stitch_into_one_panorama(tmp_path, capsys):
    """``usf-graph render`` of the four cameras' images, each through its own calibration
    (``--camera FV.json,RV.json,...``, posed in the vehicle frame), into one panorama: every
    direction shows the colour its ray was given, whichever camera saw it (a camera mounted
    on the wrong side, or mirrored, would show another)."""
    from tests.datasets.test_woodscape import _calibration, _write
    from usf_graph.cli import main

    sides = {"00001_FV": 0, "00001_RV": 180, "00001_MVL": 90, "00001_MVR": -90}
    for name, yaw in sides.items():
        _write(tmp_path, name, _calibration(yaw))
    calib = tmp_path / "calibration_data" / "calibration"
    rig = cameras.load_rig([calib / f"{n}.json" for n in sides])
    assert list(rig) == list(sides)
    images = [str(tmp_path / "rgb_images" / f"{n}.png") for n in sides]
    out = tmp_path / "car.png"
    assert main(["render", *images, "--camera", ",".join(str(calib / f"{n}.json") for n in sides),
                 "--to", "equirectangular:256x128", "--out", str(out)]) == 0
    pano = cv2.imread(str(out))[..., ::-1].astype(np.float64) / 255
    rays, _ = cameras.Equirectangular(256, 128).lens_normal_map()
    seen = pano.sum(-1) > 0
    band = np.abs(rays[..., 2]) < 0.5  # the horizon, all around the car: every camera's
    assert seen[band].all()
    want = (np.stack([rays[..., 2], rays[..., 0], rays[..., 1]], -1) + 1) / 2
    err = np.abs(pano - want)[seen]
    assert np.median(err) < 0.01 and np.percentile(err, 99) < 0.05
    with pytest.raises(ValueError, match="no pose in the rig"):
        cameras.load_rig([calib / "00001_FV.json", FIXTURES / "opencv_pinhole.yaml"])
    listed = ",".join(str(calib / f"{n}.json") for n in sides)
    capsys.readouterr()
    assert main(["camera", listed, "--all"]) == 0
    rows = capsys.readouterr().out.splitlines()[1:]
    assert [r.split()[0] for r in rows] == list(sides) and "(-1.0000, +0.0000" in rows[1]
    assert main(["camera", listed]) == 2
    assert "names several files (a rig of posed cameras): list them with --all" in \
        capsys.readouterr().err


@pytest.mark.parametrize("fov_deg, theta_max", [(120.0, 60.0), (None, None)])
def test_a_claimed_field_of_view_bounds_what_projects(fov_deg, theta_max):
    """Rays up to half of ``fov_deg`` project and those past it do not; without a claim the
    limit is where ``rho`` stops increasing (300 t - 50 t^3: at t = sqrt(2) rad)."""
    cam = RadialPoly([300.0, 0.0, -50.0], 640, 480, 1280, 966, fov_deg=fov_deg)
    limit = math.radians(theta_max) if theta_max else math.sqrt(2.0)
    assert cam.theta_max == pytest.approx(limit, abs=math.pi / 20000)  # its search step
    t = limit * np.array([0.5, 0.999, 1.001, 1.5])
    rays = np.stack([np.sin(t) * 0.6, np.sin(t) * 0.8, np.cos(t)], -1)
    uv, ok = cam.project(rays)
    assert ok.tolist() == [True, True, False, False] and np.isnan(uv[2:]).all()
