"""``usf-graph camera``: what a calibration file holds, one camera or all of them."""

from __future__ import annotations

import json
import math

from .cli_inputs import (
    calibration_files,
    camera_from_spec,
    fit_to_image,
    image_size,
    is_cubemap_spec,
    is_panorama_spec,
    read_image,
)


def _vec(a) -> str:
    return f"({a[0]:+.4f}, {a[1]:+.4f}, {a[2]:+.4f})"


def _axis(cam) -> str:
    return _vec(cam.rotation @ cam.optical_axis)


def _centre(cam) -> str:
    return "-" if cam.position is None else _vec(cam.position)


def cmd_camera(args) -> int:
    from .cameras import with_fov_and_mask

    if args.all:
        return _list_cameras(args)
    if isinstance(calibration_files(args.calib), list):
        raise ValueError(f"{args.calib!r} names several files (a rig of posed cameras): list "
                         "them with --all, or describe one file at a time")
    # a panorama without a size takes the overlaid image's
    shape = read_image(args.overlay[0]).shape if args.overlay and (
        is_panorama_spec(args.calib) or is_cubemap_spec(args.calib)) else None
    cam = camera_from_spec(args.calib, args.key, args.fov, image_shape=shape)
    if args.resize:
        cam = cam.resized(*image_size(args.resize, "--resize", "640x480"))
    cam = with_fov_and_mask(cam, None, args.image_mask)
    if args.save_colmap:
        _save_colmap({1: cam}, args.save_colmap)
    om = cam.solid_angle()
    print(f"model          {type(cam).__name__} ({cam.model})")
    print(f"image          {cam.width} x {cam.height}")
    inc = math.degrees(cam.max_incidence)  # fov_deg is twice it: every ray's angle, once
    print(f"field of view  {2 * inc:.2f} deg (max incidence {inc:.2f} deg)")
    print(f"solid angle    {om:.4f} sr = {om / (4 * math.pi):.2%} of the sphere")
    print(f"parameters     {json.dumps(cam.key()['params'])}")
    print(f"optical axis   {_axis(cam)} in the sphere frame (x forward, y left, z up)")
    if cam.position is not None:
        print(f"optical centre {_centre(cam)} in the rig's sphere frame (the file's unit)")
    if args.plot:
        from .viz import plot_lens_normal_map

        plot_lens_normal_map(cam, args.plot)
        print(f"wrote {args.plot}")
    if args.overlay:
        _overlay(cam, *args.overlay)
    if args.save:
        cam.save(args.save)
        print(f"wrote {args.save} (usf-graph YAML; read it with --camera {args.save})")
    return 0


def _overlay(cam, image_path: str, out: str) -> None:
    """``camera --overlay IMAGE OUT``: the graticule drawn on the camera's image
    (:func:`usf_graph.viz.draw_graticule`; the calibration scaled to an image resized as a
    whole)."""
    import cv2

    from .fileio import write_image
    from .viz import draw_graticule

    img = read_image(image_path)
    drawn = draw_graticule(img, fit_to_image(cam, img.shape))
    write_image(out, cv2.cvtColor(drawn, cv2.COLOR_RGB2BGR))
    print(f"wrote {out}")


def _list_cameras(args) -> int:
    """``camera --all``: one line per camera of the file."""
    from . import cameras

    if args.key is not None or args.plot or args.save or args.resize or args.overlay:
        raise ValueError("--all lists every camera of the file; leave out --key, --plot, "
                         "--overlay, --save and --resize (then pick one with --key)")
    print(f"{'key':<10} {'model':<16} {'image':>11} {'fov (deg)':>10}  {'optical axis (sphere frame)':<29} "
          "optical centre")
    found = cameras.load_all(calibration_files(args.calib))
    for key, cam in found.items():
        cam = cameras.with_fov_and_mask(cam, args.fov, args.image_mask)
        size = f"{cam.width}x{cam.height}"
        print(f"{'-' if key is None else key!s:<10} {cam.model:<16} {size:>11} "
              f"{cam.fov_deg:>10.2f}  {_axis(cam):<29} {_centre(cam)}")
    if args.save_colmap:  # COLMAP's ids where the file had them, else 1, 2, ... in its order
        ids = list(found) if all(isinstance(k, int) for k in found) else range(1, len(found) + 1)
        _save_colmap(dict(zip(ids, found.values())), args.save_colmap)
    return 0


def _save_colmap(cams: dict, path) -> None:
    from .cameras.colmap import save_text

    save_text(cams, path)
    print(f"wrote {path} (COLMAP's camera list, {len(cams)} camera{'s' * (len(cams) > 1)}; "
          "field-of-view limits, image masks and a rig's mounting are not in COLMAP's list)")
