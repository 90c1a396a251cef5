"""How far apart may a rig's cameras be? Lifting a rig at infinity against stitching it at a
distance, on procedural rooms with exact labels.

A rig of four 190-degree fisheyes looks front, left, back and right from ``--baseline``
metres off its centre (a robot's head, a car's roof). Each camera renders the room from its
own optical centre (``scenes.render`` honours ``camera.position``); the rig is lifted onto
one grid (each point from the camera looking closest), with its baseline ignored (the
distance at infinity) or stitched at 1, 2, 3 and 5 m (``RigFrontend(..., distance=D)``), and at the distance where the cameras agree best on
their overlaps (``choose_distance``, from each room's images alone). The
reference is the panorama rendered from the rig's centre; the same four cameras placed at
the centre give the floor that resampling alone costs. Per setting: the share of grid
points whose label (nearest pixel) differs from the panorama's, over all points and on the
seams (points next to one another camera fills), and the mean absolute colour error
(0-255) on the seams.

    .venv/bin/python examples/rig_parallax.py --out runs/rig_parallax [--baseline 0.15]
    .venv/bin/python examples/rig_parallax.py --checkpoint runs/seg/spherical_deeplab.pt

About a minute on 2 cores. Writes ``results.json`` and ``seams.png`` (the label errors on
the sphere, at infinity and stitched at 2 m). With ``--checkpoint`` (a ``usf-graph train
seg`` model) it also scores that segmenter through the rig on the protocol's test rooms
(``--rooms`` of them, its materials, given the true up): mIoU on the cameras' pixels at
infinity, stitched at 2 m, at the chosen distance, and with the cameras at the centre.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from usf_graph import cameras, grids, scenes
from usf_graph.cameras import DEFAULT_ROTATION
from usf_graph.frontend import RigFrontend, SphericalFrontend, choose_distance
from usf_graph.geometry import rotation_from_axis_angle

DISTANCES = (None, 1.0, 2.0, 3.0, 5.0)


def ring_rig(baseline: float, size: int = 256) -> dict:
    """Four 190-degree equidistant fisheyes looking front, left, back and right, each
    ``baseline`` metres out along its optical axis."""
    f = (size / 2) / math.radians(95)
    rig = {}
    for i, name in enumerate(("front", "left", "back", "right")):
        yaw = rotation_from_axis_angle([0.0, 0.0, 1.0], i * math.pi / 2)
        cam = cameras.KannalaBrandt(f, f, (size - 1) / 2, (size - 1) / 2, size, size,
                                    k=(0, 0, 0, 0)).with_fov(190)
        rig[name] = cam.with_rotation(yaw @ DEFAULT_ROTATION).with_position(
            yaw @ [baseline, 0.0, 0.0])
    return rig


def lift_labels(fe, views) -> np.ndarray:
    """Grid labels from each camera's label image, nearest pixel."""
    return fe.lift([v.label[..., None].astype(np.float64) for v in views]).numpy()[:, 0]


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="runs/rig_parallax")
    ap.add_argument("--baseline", type=float, default=0.15, help="metres from the centre")
    ap.add_argument("--rooms", type=int, default=6)
    ap.add_argument("--level", type=int, default=5, help="icosahedral grid level")
    ap.add_argument("--size", type=int, default=256, help="fisheye image size")
    ap.add_argument("--checkpoint", default=None, help="also score this segmenter through the rig")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    g = grids.icosahedral(args.level)
    rig = ring_rig(args.baseline, args.size)
    pano = cameras.Equirectangular(4 * args.size, 2 * args.size)
    ref_fe = SphericalFrontend(pano, g, interpolation="nearest")
    centred = {n: c.with_position(None) for n, c in rig.items()}
    settings = {"no baseline (the floor)": (centred, None)} | {
        "at infinity" if d is None else f"stitched at {d:g} m": (rig, d) for d in DISTANCES}
    fes = {k: RigFrontend(r, g, interpolation="nearest", distance=d) for k, (r, d) in settings.items()}
    colour = {k: RigFrontend(r, g, distance=d) for k, (r, d) in settings.items()}
    src = fes["at infinity"].source
    i, j = fes["at infinity"].edge_index
    seams = np.zeros(len(g), bool)
    seams[j[src[i] != src[j]].numpy()] = True
    auto = "stitched where the seams agree"
    wrong = {k: [] for k in (*settings, auto)}
    col_err = {k: [] for k in (*settings, auto)}
    chosen = []
    coarse = grids.icosahedral(min(args.level, 4))
    maps = {}
    for k in tqdm(range(args.rooms), desc="rooms", disable=args.no_progress):
        scene = scenes.make_room(seed=0, index=k)
        p, R = scene.viewpoint(0)
        ref = scenes.render(scene, pano, position=p, rotation=R, boxes=False)
        truth = ref_fe.lift(ref.label[..., None].astype(np.float64)).numpy()[:, 0]
        truth_rgb = SphericalFrontend(pano, g).lift(ref.rgb.astype(np.float64)).numpy()
        shots = {id(r): [scenes.render(scene, c, position=p, rotation=R, boxes=False)
                         for c in r.values()] for r in (rig, centred)}
        for name, (r, _) in settings.items():
            views = shots[id(r)]
            lab = lift_labels(fes[name], views)
            wrong[name].append(lab != truth)
            rgb = colour[name].lift([v.rgb.astype(np.float64) for v in views]).numpy()
            col_err[name].append(np.abs(rgb - truth_rgb).mean(1))
            if k == 0:
                maps[name] = lab != truth
        # the distance chosen from this room's images alone, by the seams' agreement
        d, _ = choose_distance(rig, coarse, [v.rgb for v in shots[id(rig)]])
        chosen.append(d)
        fe = RigFrontend(rig, g, interpolation="nearest", distance=d)
        wrong[auto].append(lift_labels(fe, shots[id(rig)]) != truth)
        rgb = RigFrontend(rig, g, distance=d).lift([v.rgb.astype(np.float64) for v in shots[id(rig)]])
        col_err[auto].append(np.abs(rgb.numpy() - truth_rgb).mean(1))
    res = {"baseline_m": args.baseline, "grid": g.spec, "rooms": args.rooms,
           "seam_share": float(seams.mean()), "settings": {}}
    print(f"rig of 4 fisheyes, {args.baseline} m off the centre, {args.rooms} rooms, {g.spec}; "
          f"seams: {seams.mean():.1%} of the sphere")
    print(f"{'':>30s} {'labels wrong':>13s} {'on the seams':>13s} {'colour err (seams)':>19s}")
    for name in wrong:
        w, c = np.stack(wrong[name]), np.stack(col_err[name])
        r = {"labels_wrong": float(w.mean()), "labels_wrong_seams": float(w[:, seams].mean()),
             "colour_err_seams": float(c[:, seams].mean())}
        res["settings"][name] = r
        print(f"{name:>30s} {r['labels_wrong']:13.2%} {r['labels_wrong_seams']:13.2%} "
              f"{r['colour_err_seams']:19.2f}")
    res["chosen_m"] = chosen
    print("distances chosen from the seams: " + ", ".join("infinity" if d is None else f"{d:.2f} m"
                                                         for d in chosen))
    if args.checkpoint:
        res["model"] = score_model(args.checkpoint, rig, args.rooms, args.no_progress)
    (out / "results.json").write_text(json.dumps(res, indent=1))
    _plot(g, maps, out / "seams.png")
    print(f"wrote {out / 'results.json'} and {out / 'seams.png'}")
    return res


def score_model(path, rig: dict, rooms: int, quiet: bool) -> dict:
    """A segmenter's mIoU on the rig cameras' pixels over the protocol's first ``rooms`` test
    rooms (seed 1, the test rooms of seed 0; the model's materials), given the true up."""
    from usf_graph.datasets.rooms import view_pose
    from usf_graph.train.apply import segment_image
    from usf_graph.train.checkpoints import load_protocol_model
    from usf_graph.train.seg_metrics import confusion_matrix, scores

    ckpt = load_protocol_model(path).require("seg", spherical=True)
    model, materials = ckpt.model.eval(), ckpt.config.get("materials")
    run = Path(path).with_name("results.json")  # the protocol's record of its rooms
    if materials is None and run.is_file():
        materials = json.loads(run.read_text()).get("materials")
    materials = materials or "random"
    centred = {n: c.with_position(None) for n, c in rig.items()}
    names = ("cameras at the centre", "at infinity", "stitched at 2 m", "stitched where the seams agree")
    conf = {n: 0 for n in names}
    g4 = grids.icosahedral(4)
    for k in tqdm(range(rooms), desc="rooms (model)", disable=quiet):
        scene = scenes.make_room(1, k, materials=materials)
        p, R = view_pose(scene, "none", k, 1)
        views = {id(r): [scenes.render(scene, c, position=p, rotation=R, boxes=False)
                         for c in r.values()] for r in (rig, centred)}
        apart = views[id(rig)]
        d, _ = choose_distance(rig, g4, [v.rgb for v in apart])
        for name, r, vs in ((names[0], centred, views[id(centred)]), (names[1], rig, apart),
                            (names[2], cameras.stitch_at(rig, 2.0), apart),
                            (names[3], cameras.stitch_at(rig, d) if d else rig, apart)):
            labels = segment_image(model, [v.rgb for v in vs], r, up=[0.0, 0.0, 1.0])["labels"]
            for lab, v in zip(labels, vs):
                conf[name] = conf[name] + confusion_matrix(lab, v.label, 13)
    out = {n: scores(c)["mIoU"] for n, c in conf.items()}
    print(f"{path} through the rig, {rooms} test rooms ({materials} materials), given the true "
          "up: mIoU on the cameras' pixels")
    for n, v in out.items():
        print(f"{n:>30s} {100 * v:6.2f}")
    return out


def _plot(g, maps, path) -> None:
    import matplotlib.pyplot as plt

    from usf_graph.viz import mollweide

    fig, axes = plt.subplots(1, 2, figsize=(12, 3.4), subplot_kw={"projection": "mollweide"})
    for ax, name in zip(axes, ("at infinity", "stitched at 2 m")):
        mollweide(ax, g.pos.numpy(), maps[name].astype(float), cmap="Reds", s=2,
                  title=f"labels unlike the centre's panorama (red), {name}")
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)


if __name__ == "__main__":
    main()
