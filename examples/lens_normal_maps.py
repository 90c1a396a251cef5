"""Lens normal maps for several real lens models, and a fisheye view synthesized from a panorama.

Run: ``.venv/bin/python examples/lens_normal_maps.py --out runs/lens``. Writes one PNG per
camera (rays as RGB plus sphere coverage), ``fisheye_from_pano.png`` and
``rig_on_sphere.png`` (two back-to-back fisheyes of a Kalibr rig lifted onto one sphere).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from usf_graph import cameras, grids
from usf_graph.frontend import RigFrontend, render
from usf_graph.viz import labelled_panorama, mollweide, plot_lens_normal_map

RIG = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "kalibr_rig.yaml"


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
    pano = labelled_panorama()
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
    # a rig: two 190-degree fisheyes back to back (Kalibr camchain), one sphere
    rig = {n: c.with_fov(190) for n, c in cameras.load_rig(RIG).items()}
    views = [render(pano, cameras.Equirectangular(*pano.shape[1::-1]), c) for c in rig.values()]
    fe = RigFrontend(rig, grids.icosahedral(6))
    x = fe.lift(views)
    fig = plt.figure(figsize=(15, 4))
    for i, (n, v) in enumerate(zip(rig, views)):
        a = fig.add_subplot(1, 4, i + 1)
        a.imshow(np.clip(v, 0, 1))
        a.set_title(f"{n} ({'front' if i == 0 else 'back'})")
        a.axis("off")
    a = fig.add_subplot(1, 2, 2, projection="mollweide")
    mollweide(a, fe.grid.pos, x, fe.mask, s=3, title="both on one sphere (seen from the centre)")
    fig.savefig(out / "rig_on_sphere.png", dpi=100, bbox_inches="tight")
    print(f"rig lifted onto one sphere -> {out / 'rig_on_sphere.png'}")


if __name__ == "__main__":
    main()
