"""Lens normal maps for several real lens models, and a fisheye view synthesized from a panorama.

Run: ``.venv/bin/python examples/lens_normal_maps.py --out runs/lens``. Writes one PNG per
camera (rays as RGB plus sphere coverage) and ``fisheye_from_pano.png``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import matplotlib.pyplot as plt
import numpy as np

from usf_graph import cameras
from usf_graph.frontend import render
from usf_graph.geometry import to_latlon
from usf_graph.viz import plot_lens_normal_map


def example_cameras() -> dict:
    """A few lenses with realistic parameters (640x480 unless noted)."""
    return {
        "pinhole_radtan": cameras.Pinhole(460.0, 460.0, 320.0, 240.0, 640, 480,
                                          dist=(-0.28, 0.07, 1e-4, -2e-4)),
        "kannala_brandt_200deg": cameras.KannalaBrandt(
            190.0, 190.0, 320.0, 320.0, 640, 640, k=(0.02, -0.005, 0.001, -0.0001), fov_deg=200),
        "mei_omni": cameras.Mei(700.0, 700.0, 320.0, 240.0, 640, 480, xi=1.6),
        "double_sphere_wide": cameras.DoubleSphere(160.0, 160.0, 320.0, 320.0, 640, 640,
                                                     xi=-0.2, alpha=0.6),
        "equirectangular": cameras.Equirectangular(512, 256),
    }


def checkerboard_panorama(width: int = 1024, height: int = 512) -> np.ndarray:
    """A latitude/longitude checkerboard with a colour ramp and FRONT/LEFT/RIGHT labels, easy
    to read after re-imaging."""
    pano = cameras.Equirectangular(width, height)
    rays, _ = pano.lens_normal_map()
    lat, lon = to_latlon(rays.reshape(-1, 3))
    check = ((np.floor(lat / np.radians(15)) + np.floor(lon / np.radians(15))) % 2).reshape(height, width)
    ramp = ((lon.reshape(height, width) + np.pi) / (2 * np.pi))
    img = np.stack([check, ramp, 1 - check * ramp], -1).astype(np.float32)
    # labels where the viewer looks forward, left and right: they must read correctly in
    # every view made from the panorama (a mirrored convention would flip them)
    ink = np.zeros((height, width), np.uint8)  # 128: outline, 255: letters
    for text, lon0 in (("FRONT", 0.0), ("LEFT", np.pi / 2), ("RIGHT", -np.pi / 2)):
        (u, v), _ = pano.project(np.array([np.cos(lon0), np.sin(lon0), 0.0]))
        (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 1.5, 4)
        org = (int(u - tw / 2), int(v + th / 2))
        cv2.putText(ink, text, org, cv2.FONT_HERSHEY_SIMPLEX, 1.5, 128, 10, cv2.LINE_AA)
        cv2.putText(ink, text, org, cv2.FONT_HERSHEY_SIMPLEX, 1.5, 255, 4, cv2.LINE_AA)
    outline = np.clip(ink / 128.0, 0, 1)[..., None]
    return (img * (1 - outline) + np.clip(ink / 127.0 - 1, 0, 1)[..., None]).astype(np.float32)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="runs/lens_normal_maps")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name, cam in example_cameras().items():
        plot_lens_normal_map(cam, out / f"{name}.png")
        print(f"{name:24s} FOV {cam.fov_deg:6.1f} deg  covers {cam.solid_angle() / (4 * np.pi):6.1%}"
              f" of S2  -> {out / (name + '.png')}")
    pano = checkerboard_panorama()
    fish = cameras.KannalaBrandt(170.0, 170.0, 320.0, 320.0, 640, 640, k=(0, 0, 0, 0), fov_deg=190)
    view = render(pano, cameras.Equirectangular(*pano.shape[1::-1]), fish)
    fig, ax = plt.subplots(1, 2, figsize=(12, 4), gridspec_kw={"width_ratios": [2, 1]})
    ax[0].imshow(pano)
    ax[0].set_title("equirectangular panorama")
    ax[1].imshow(np.clip(view, 0, 1))
    ax[1].set_title("190 deg fisheye synthesized through the sphere")
    for a in ax:
        a.axis("off")
    fig.savefig(out / "fisheye_from_pano.png", dpi=100, bbox_inches="tight")
    print(f"fisheye view from panorama -> {out / 'fisheye_from_pano.png'}")


if __name__ == "__main__":
    main()
