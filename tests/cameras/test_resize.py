"""A calibration for resized images: the same lens on another pixel grid."""

import cv2
import numpy as np
import pytest

from tests.helpers import FIXTURES
from usf_graph import cameras


def models():
    return {
        "pinhole": cameras.Pinhole(400, 380, 319.5, 239.5, 640, 480,
                                   dist=[-0.2, 0.05, 0.001, -0.001, 0.01]),
        "division": cameras.Division(300, 310, 320.3, 241.2, 640, 480, k=-0.2),
        "fisheye": cameras.Fisheye(200, 319.5, 239.5, 640, 480, model="equisolid"),
        "kannala_brandt": cameras.KannalaBrandt(250, 251, 320.2, 240.7, 640, 480,
                                                k=(0.01, -0.005, 0.001, 0.0)),
        "fov": cameras.FOV(300, 300, 320, 240, 640, 480, omega=0.9),
        "radial_poly": cameras.RadialPoly([170.0, -12.0, 21.0, -3.2], 320.4, 239.1, 640, 480,
                                          aspect_ratio=1.05),
        "mei": cameras.Mei(500, 505, 320, 240, 640, 480, xi=0.9, dist=(0.01, 0, 0.001, 0),
                           skew=0.5),
        "double_sphere": cameras.DoubleSphere(300, 300, 320, 240, 640, 480, xi=-0.2, alpha=0.6),
        "eucm": cameras.EUCM(300, 300, 320, 240, 640, 480, alpha=0.6, beta=1.1),
        "ocamcalib": cameras.load(FIXTURES / "calib_results.txt"),
        "panorama": cameras.Equirectangular(640, 320),
    }


def rays_in_front(n=4000, seed=0):
    r = np.random.default_rng(seed).normal(size=(n, 3))
    r[:, 2] = np.abs(r[:, 2]) + 0.3
    return r / np.linalg.norm(r, axis=1, keepdims=True)


@pytest.mark.parametrize("name", list(models()))
@pytest.mark.parametrize("scale", [0.5, 0.75, 1.6])
def test_every_point_lands_where_resizing_moves_its_pixel(name, scale):
    """(u', v') = ((u + 0.5) s - 0.5, (v + 0.5) s - 0.5) for every ray both see."""
    cam = models()[name]
    w, h = round(cam.width * scale), round(cam.height * scale)
    new = cam.resized(w, h)
    assert (new.width, new.height) == (w, h) and type(new) is type(cam)
    rays = rays_in_front() if name != "panorama" else np.random.default_rng(1).normal(size=(4000, 3))
    uv, ok = cam.project(rays)
    uv2, ok2 = new.project(rays)
    both = ok & ok2
    assert both.mean() > 0.3
    s = np.array([w / cam.width, h / cam.height])
    np.testing.assert_allclose(uv2[both], (uv[both] + 0.5) * s - 0.5, atol=1e-6)
    back, valid = new.unproject(uv2[both])  # and the rays come back
    assert valid.all()
    np.testing.assert_allclose(back, rays[both] / np.linalg.norm(rays[both], axis=1, keepdims=True),
                               atol=1e-8)


@pytest.mark.parametrize("name", [n for n in models() if n not in ("fisheye", "ocamcalib", "panorama")])
def test_axes_may_scale_apart_where_the_model_has_two_focal_lengths(name):
    cam = models()[name]
    new = cam.resized(320, 360)  # 0.5 across, 0.75 down
    uv, ok = cam.project(rays_in_front())
    uv2, ok2 = new.project(rays_in_front())
    both = ok & ok2
    np.testing.assert_allclose(uv2[both], (uv[both] + 0.5) * [0.5, 0.75] - 0.5, atol=1e-6)


@pytest.mark.parametrize("name", ["fisheye", "ocamcalib"])
def test_one_focal_length_needs_one_factor(name):
    with pytest.raises(ValueError, match="resize its images by one factor"):
        models()[name].resized(320, 360)


def test_the_resized_camera_sees_what_cv2_resize_makes_of_the_image():
    """OpenCV is the reference: an image of a smooth scene through a distorted pinhole,
    halved by ``cv2.resize(INTER_AREA)``, matches that scene seen through the resized
    calibration; the principal point moved as pixels are (not just scaled) matters."""
    cam = models()["pinhole"]

    def view(c):
        v, u = np.mgrid[:c.height, :c.width]
        r, ok = c.unproject(np.stack([u, v], -1).astype(np.float64))
        return np.where(ok, 0.5 + 0.5 * np.sin(9 * r[..., 0]) * np.cos(7 * r[..., 1]), 0.0)

    half = cv2.resize(view(cam), (320, 240), interpolation=cv2.INTER_AREA)
    err = np.abs(half - view(cam.resized(320, 240)))[8:-8, 8:-8].mean()
    naive = cameras.Pinhole(200, 190, 0.5 * cam.cx, 0.5 * cam.cy, 320, 240, dist=cam.dist[:5])
    err_naive = np.abs(half - view(naive))[8:-8, 8:-8].mean()
    assert err < 2e-4 and err_naive > 5 * err, (err, err_naive)


def test_a_ray_table_resamples_through_its_own_interpolation():
    """A lens normal map made from a Kannala-Brandt lens, resized, gives the rays that the
    resized lens itself gives, to the table's interpolation error."""
    kb = cameras.KannalaBrandt(60, 60, 63.5, 47.5, 128, 96, k=(0.01, -0.005, 0.001, 0.0))
    v, u = np.mgrid[:96, :128]
    rays, ok = kb.unproject(np.stack([u, v], -1).astype(np.float64))
    table = cameras.LensNormalMap(rays, ok).resized(64, 48)
    v, u = np.mgrid[:48, :64]
    got, ok_t = table.unproject(np.stack([u, v], -1).astype(np.float64))
    want, ok_k = kb.resized(64, 48).unproject(np.stack([u, v], -1).astype(np.float64))
    both = ok_t & ok_k
    assert both.mean() > 0.9
    assert np.degrees(np.arccos(np.clip((got * want).sum(-1)[both], -1, 1))).max() < 0.05


def test_mounting_field_of_view_and_mask_follow():
    cam = models()["kannala_brandt"].with_fov(150).with_position([0.1, 0, 0]).with_distance(2.0)
    mask = np.ones((480, 640), bool)
    mask[:, :320] = False
    cam = cam.with_image_mask(mask).with_rotation(cameras.DEFAULT_ROTATION[:, [1, 0, 2]] * [1, 1, -1])
    new = cam.resized(320, 240)
    assert np.array_equal(new.rotation, cam.rotation) and new.fov_limit == cam.fov_limit
    assert np.array_equal(new.position, cam.position) and new.distance == 2.0
    assert new.image_mask.shape == (240, 320) and not new.image_mask[:, :160].any()
    assert new.image_mask[:, 160:].all()
    for size, said in (((0, 240), "width"), ((640.7, 480), "width"), ((320, float("nan")), "height")):
        with pytest.raises(ValueError, match=f"{said} must be a positive integer number of pixels"):
            cam.resized(*size)  # 640.7 was truncated to 640
