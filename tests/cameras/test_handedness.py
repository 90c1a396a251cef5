"""Left and right agree across cameras: a panorama's right is the viewer's right, as in a
pinhole or fisheye image, and text reads the right way round through the sphere."""

import math

import cv2
import numpy as np
import pytest

from usf_graph import cameras as C
from usf_graph.frontend import render

W, H = 1024, 512
F = W / (2 * math.pi)  # pixels per radian at the panorama's centre


def perspective_cameras(size=256):
    c = (size - 1) / 2
    return {"pinhole": C.Pinhole(F, F, c, c, size, size),
            "fisheye": C.Fisheye(F, c, c, size, size, model="equidistant"),
            "kannala-brandt": C.KannalaBrandt(F, F, c, c, size, size, k=(0.01, 0, 0, 0))}


@pytest.mark.parametrize("name", ["pinhole", "fisheye", "kannala-brandt"])
def test_right_of_centre_is_right_in_the_panorama(name):
    cam, pano = perspective_cameras()[name], C.Equirectangular(W, H)
    c = (cam.width - 1) / 2
    uv = np.array([[c + 60, c], [c - 60, c], [c, c - 60]])  # right, left, up
    rays, ok = cam.unproject(uv)
    world = rays @ cam.rotation.T
    assert ok.all() and world[0, 1] < 0 < world[1, 1] and world[2, 2] > 0  # y is left, z up
    puv, ok = pano.project(world)
    assert ok.all()
    assert puv[0, 0] > W / 2 > puv[1, 0]  # right stays right, left stays left
    assert puv[2, 1] < H / 2  # up stays up


def text_image(size, scale, thickness):
    img = np.zeros((size, size), np.uint8)
    (tw, th), _ = cv2.getTextSize("R2 usf", cv2.FONT_HERSHEY_SIMPLEX, scale, thickness)
    org = ((size - tw) // 2, (size + th) // 2)
    cv2.putText(img, "R2 usf", org, cv2.FONT_HERSHEY_SIMPLEX, scale, 255, thickness, cv2.LINE_AA)
    return img


def ncc(a, b):
    a, b = a.astype(np.float64).ravel(), b.astype(np.float64).ravel()
    a, b = a - a.mean(), b - b.mean()
    return float(a @ b / np.sqrt((a @ a) * (b @ b)))


@pytest.mark.parametrize("name", ["pinhole", "fisheye", "kannala-brandt"])
def test_text_in_a_panorama_reads_correctly_through_another_lens(name):
    # write text at the panorama's centre (forward), view it through another lens
    pano = np.zeros((H, W), np.uint8)
    patch = text_image(256, 1.6, 3)
    pano[H // 2 - 128:H // 2 + 128, W // 2 - 128:W // 2 + 128] = patch
    cam = perspective_cameras()[name]
    view = render(pano, C.Equirectangular(W, H), cam)
    straight, mirrored = ncc(view, patch), ncc(view, cv2.flip(patch, 1))
    assert straight > 0.85 and straight - mirrored > 0.4, (straight, mirrored)
    # and back: text written in the lens's image reads correctly in the panorama
    back = render(patch, cam, C.Equirectangular(W, H))[H // 2 - 128:H // 2 + 128,
                                                        W // 2 - 128:W // 2 + 128]
    straight, mirrored = ncc(back, patch), ncc(back, cv2.flip(patch, 1))
    assert straight > 0.85 and straight - mirrored > 0.4, (straight, mirrored)
