"""``usf-graph lift`` and ``usf-graph render``: an image (or a rig's images) through its
camera onto a grid, or into another camera's pixels."""

from __future__ import annotations

from pathlib import Path

from .cli_inputs import (
    camera_from_spec,
    is_panorama_spec,
    leveled,
    read_image,
    rig_from_spec,
    split_frame,
)


def read_images(args) -> list:
    """The images of ``args.image``; with ``args.split``, the one image cut into the rig's
    cameras' images, side by side (a dual-fisheye 360 camera's frame)."""
    images = [read_image(p) for p in args.image]
    if not getattr(args, "split", False):
        return images
    from .cameras import load_rig

    if len(images) != 1:
        raise ValueError("--split cuts one image into the rig's cameras' images; give one")
    return split_frame(images[0], len(load_rig(args.camera, key=args.key)), args.camera)


def _check_one_or_rig(args, rig: bool) -> None:
    """``--level`` reads one camera's image; ``--distance`` stitches a rig's cameras."""
    if rig and (args.level or args.up is not None):
        raise ValueError("--level reads one camera's image; a rig's images are stitched as the "
                         "rig is mounted (level its sphere from its IMU: usf-graph predict "
                         "--rig --imu)")
    if not rig and args.distance is not None:
        raise ValueError("--distance stitches a rig's cameras; one image is seen from its own "
                         "camera's centre: give the rig's images to use it")


def cmd_lift(args) -> int:
    from . import grids
    from .frontend import RigFrontend, SphericalFrontend, save_lifted

    images = read_images(args)
    grid = grids.from_spec(args.grid)
    _check_one_or_rig(args, len(images) > 1)
    if len(images) > 1:
        rig = rig_from_spec(args.camera, args.fov, args.image_mask, args.key, args.distance,
                            images, grid)
        fe = RigFrontend(rig, grid, interpolation=args.interpolation, blend=args.blend,
                         radius=args.radius)
        x = fe.lift(images)
    else:
        cam = camera_from_spec(args.camera, args.key, args.fov, args.image_mask, images[0].shape)
        cam = leveled(cam, images[0], args)
        fe = SphericalFrontend(cam, grid, interpolation=args.interpolation, radius=args.radius)
        x = fe.lift(images[0])
    print(f"{fe}\n-> x {tuple(x.shape)}, {int(fe.mask.sum())}/{len(grid)} points visible")
    if args.out:
        save_lifted(args.out, x, fe, source=" ".join(args.image))
        size = Path(args.out).stat().st_size
        print(f"wrote {args.out} ({size / 1e6:.2f} MB: signal, mask and geometry spec; "
              "read it with usf_graph.frontend.load_lifted)")
    if args.preview:
        from .viz import plot_sphere

        v = x.float()  # RGB images in colour, other channel counts as their mean
        if v.shape[-1] == 4:
            v = v[:, :3]
        plot_sphere(grid.pos, v if v.shape[-1] == 3 else v.mean(-1), fe.mask, args.preview,
                    title=" + ".join(args.image))
        print(f"wrote {args.preview}")
    return 0


def cmd_render(args) -> int:
    import cv2
    import numpy as np

    from .frontend import render, render_rig

    images = read_images(args)
    img = images[0]
    if len(images) > 1 and is_panorama_spec(args.to) and ":" not in args.to:
        raise ValueError("a rig's images have no one width to take: give the panorama's size, "
                         "--to equirectangular:WIDTHxHEIGHT")
    # a target is the camera asked for, not fitted to the source image; a panorama without
    # a size gets the source's width, at 2:1
    dst = camera_from_spec(args.to, args.to_key,
                           image_shape=(img.shape[1] // 2, img.shape[1]) if is_panorama_spec(args.to) else None)
    _check_one_or_rig(args, len(images) > 1)
    if len(images) > 1:
        rig = rig_from_spec(args.camera, args.fov, args.image_mask, args.key, args.distance, images)
        out = render_rig(images, rig, dst, blend=args.blend, interpolation=args.interpolation)
        print(f"rig of {len(rig)} ({', '.join(rig)}) -> {type(dst).__name__} {dst.width}x{dst.height}, "
              f"blend {args.blend}")
    else:
        src = camera_from_spec(args.camera, args.key, args.fov, args.image_mask, img.shape)
        src = leveled(src, img, args)  # the source mounted level: the target sees a level scene
        out = render(img, src, dst, interpolation=args.interpolation)
        print(f"{type(src).__name__} {src.width}x{src.height} -> {type(dst).__name__} "
              f"{dst.width}x{dst.height}")
    if out.ndim == 3 and out.shape[2] in (3, 4):
        out = cv2.cvtColor(out, cv2.COLOR_RGB2BGR if out.shape[2] == 3 else cv2.COLOR_RGBA2BGRA)
    if args.out.endswith(".npy"):
        np.save(args.out, out)
    elif not cv2.imwrite(args.out, out):
        raise ValueError(f"cannot write {args.out}: use an image suffix OpenCV knows (.png, .jpg)")
    print(f"wrote {args.out}")
    return 0
