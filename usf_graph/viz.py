"""Plots: spherical signals (Mollweide, 3-D), lens normal maps, task results."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from .fileio import atomic_write  # noqa: E402
from .geometry import to_latlon  # noqa: E402


def _np(a):
    return a.detach().cpu().numpy() if isinstance(a, torch.Tensor) else np.asarray(a)


def _colours(values, n):
    """``[N]``/``[N, 1]`` -> scalars for a colormap; ``[N, 3]`` -> RGB in [0, 1] (scaled by
    the maximum when it exceeds 1, e.g. 8-bit pixels)."""
    v = _np(values).astype(np.float64).reshape(n, -1)
    if v.shape[1] != 3:
        return v[:, 0], False
    top = v.max() if v.size else 1.0
    return np.clip(v / (top if top > 1 else 1.0), 0, 1), True


def mollweide(ax, pos, values, mask=None, s=4, cmap="viridis", title=None):
    """Scatter a spherical signal on a Mollweide axis; hidden points in light grey.
    ``values`` ``[N]`` use ``cmap``; ``[N, 3]`` are drawn as RGB colours. The sphere is
    seen from its centre, as the cameras see it: forward (+x) in the middle, longitude
    decreasing to the right (left, +y, is on the left)."""
    lat, lon = to_latlon(_np(pos).astype(np.float64))
    lon = -lon  # matplotlib draws its longitude increasing to the right
    v, rgb = _colours(values, len(lat))
    m = np.ones(len(v), bool) if mask is None else _np(mask).astype(bool)
    ax.scatter(lon[~m], lat[~m], c="0.85", s=s, linewidths=0)
    sc = ax.scatter(lon[m], lat[m], c=v[m], s=s, linewidths=0, **({} if rgb else {"cmap": cmap}))
    ax.grid(True, alpha=0.3)
    ax.set_xticklabels([])
    if title:
        ax.set_title(title, fontsize=9)
    return sc


def plot_sphere(pos, values, mask=None, path=None, title=None):
    """Mollweide map and 3-D scatter of a signal (``[N]``, or ``[N, 3]`` as RGB) side by
    side; saved to ``path``."""
    fig = plt.figure(figsize=(10, 4))
    ax = fig.add_subplot(1, 2, 1, projection="mollweide")
    sc = mollweide(ax, pos, values, mask, title=title)
    p = _np(pos)
    v, rgb = _colours(values, len(p))
    if not rgb:
        fig.colorbar(sc, ax=ax, shrink=0.6)
    ax3 = fig.add_subplot(1, 2, 2, projection="3d")
    ax3.scatter(p[:, 0], p[:, 1], p[:, 2], c=v, s=2)
    ax3.set_box_aspect((1, 1, 1))
    ax3.set_xlabel("x (forward)")
    ax3.set_ylabel("y (left)")
    ax3.set_zlabel("z (up)")
    return _finish(fig, path)


def plot_lens_normal_map(cam, path=None, n_cover: int = 20000):
    """Rays as RGB ((r + 1) / 2) and the covered part of the sphere."""
    lnm, valid = cam.lens_normal_map()
    rgb = np.where(valid[..., None], (lnm + 1) / 2, 0.0)
    fig = plt.figure(figsize=(10, 4))
    ax = fig.add_subplot(1, 2, 1)
    ax.imshow(np.clip(rgb, 0, 1))
    ax.set_title(f"{type(cam).__name__}: lens normal map (x, y, z -> R, G, B)", fontsize=9)
    ax.axis("off")
    from .grids import fibonacci

    pts = fibonacci(n_cover).pos.numpy()
    _, seen = cam.sees(pts)
    ax2 = fig.add_subplot(1, 2, 2, projection="mollweide")
    mollweide(ax2, pts, seen.astype(float), seen, s=1, cmap="autumn",
              title=f"coverage: {cam.solid_angle() / (4 * math.pi):.1%} of the sphere, "
                    f"FOV {cam.fov_deg:.0f} deg")
    return _finish(fig, path)


def plot_mnist_results(results: dict, model, test_r, path, n: int = 6):
    """Accuracy bars (NR/NR vs NR/R) and a few rotated digits with predictions."""
    fig = plt.figure(figsize=(12, 5))
    ax = fig.add_subplot(1, n // 2 + 1, 1)
    names = [k for k in ("spherical", "planar") if k in results]
    w = 0.35
    for i, proto in enumerate(("NR", "R")):
        vals = [100 * results[k][proto] for k in names]
        bars = ax.bar(np.arange(len(names)) + (i - 0.5) * w, vals, w, label=f"NR/{proto}")
        ax.bar_label(bars, fmt="%.1f", fontsize=7)
    ax.set_xticks(range(len(names)), names)
    ax.set_ylim(0, 105)
    ax.set_ylabel("test accuracy (%)")
    ax.legend(fontsize=8)
    ax.set_title("trained unrotated", fontsize=9)
    model.eval()
    # one digit of each of the first n classes present (the test set is sorted by label)
    labels = test_r.y.tolist()
    pick = [labels.index(c) for c in sorted(set(labels))][:n]
    pick += [i for i in range(len(labels)) if i not in pick][:n - len(pick)]
    with torch.no_grad():
        pred = model(test_r.x[pick]).argmax(-1)
    for i, k in enumerate(pick):
        a = fig.add_subplot(2, n // 2 + 1, (i // (n // 2)) * (n // 2 + 1) + i % (n // 2) + 2,
                            projection="mollweide")
        mollweide(a, test_r.grid.pos, test_r.x[k], s=2, cmap="gray",
                  title=f"label {int(test_r.y[k])}, pred {int(pred[i])}")
        a.set_yticklabels([])
    return _finish(fig, path)


def _finish(fig, path, rect=None):
    fig.tight_layout(rect=rect)
    if path is not None:  # atomically: a figure is never seen half written
        atomic_write(path, lambda f: fig.savefig(f, dpi=110, format=Path(path).suffix[1:] or None))
        plt.close(fig)
    return fig


def labelled_panorama(width: int = 1024, height: int = 512) -> np.ndarray:
    """A float32 RGB equirectangular test picture: a 15-degree latitude/longitude checkerboard,
    a colour ramp in longitude, and FRONT/LEFT/RIGHT written where the viewer looks forward
    (+x), left (+y) and right. Re-image it through any camera (:func:`frontend.render`) to
    check conventions by looking: the words must read correctly in every view."""
    import cv2

    from .cameras import Equirectangular

    pano = Equirectangular(width, height)
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


# box colours (RGB) of the detection figures: true boxes, detections, true boxes the camera cuts
TRUTH, DETECTION, CUT = (0, 255, 0), (255, 255, 0), (255, 60, 60)


def _draw_curve(out: np.ndarray, camera, points: np.ndarray, colour, thickness: int = 2,
                scale: int = 1) -> list:
    """Draws the sphere-frame curve ``points [M, 3]`` on ``out`` (the camera's image enlarged
    ``scale`` times) where ``camera`` sees it, cut where it does not or where a panorama
    wraps; returns the drawn runs of pixel points."""
    import cv2

    uv, seen = camera.sees(points)
    uv = (uv + 0.5) * scale - 0.5  # pixel centres of the enlarged image
    runs, cur = [], []
    for (u, v), ok in zip(uv, seen):
        if ok and cur and abs(u - cur[-1][0]) > scale * camera.width / 2:  # panorama seam
            runs.append(cur)
            cur = []
        if ok:
            cur.append((u, v))
        elif cur:
            runs.append(cur)
            cur = []
    runs.append(cur)
    for r in runs:
        if len(r) > 1:
            pts = np.round(np.array(r) * 4).astype(np.int32)  # 2 fractional bits
            cv2.polylines(out, [pts], False, colour, thickness, cv2.LINE_AA, shift=2)
    return runs


def draw_boxes(image: np.ndarray, camera, boxes, names=None, colour=DETECTION,
               thickness: int = 2, scale: int = 1) -> np.ndarray:
    """A copy of ``image [H, W, 3]`` uint8 with spherical ``boxes [K, 5]`` (the camera's
    sphere frame, radians) drawn as their four great-circle edges, cut where the camera
    does not see them or where a panorama wraps, and labelled with ``names``. ``scale``:
    the image enlarged this many times first (nearest), so that boxes and names on a small
    image stay legible."""
    import cv2

    from .ops.boxes import box_edges

    out = np.ascontiguousarray(image.copy())
    if scale != 1:
        out = cv2.resize(out, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    boxes = _np(boxes).reshape(-1, 5)
    for k, b in enumerate(boxes):
        runs = _draw_curve(out, camera, box_edges(b, 64), colour, thickness, scale)
        top = max((r for r in runs if r), key=len, default=None)
        if names is not None and top:
            u, v = min(top, key=lambda q: q[1])
            cv2.putText(out, str(names[k]), (int(u), max(int(v) - 4, 10)), cv2.FONT_HERSHEY_SIMPLEX,
                        0.4, colour, 1, cv2.LINE_AA)
    return out


#: Colours (RGB) of :func:`draw_graticule`: the horizon, the other circles, the edge of view.
HORIZON, GRATICULE, VIEW_EDGE = (255, 220, 0), (255, 255, 255), (255, 60, 60)


def draw_graticule(image: np.ndarray, camera, step: float = 15.0) -> np.ndarray:
    """A copy of ``image [H, W(, 3)]`` (uint8, uint16, or floats in [0, 1]) with the parallels and
    meridians of ``camera``'s sphere frame every ``step`` degrees (the horizon thicker, in
    yellow), the meridian straight ahead (x) labelled 0 and the edge of the camera's
    usable view in red: a check of a calibration and its mounting by eye. Through any lens
    the meridians are vertical great circles, so on a level camera (or with the IMU's
    mounting) they follow the scene's verticals and the horizon lies on the real one; a
    fisheye's red edge should lie on its image circle."""
    import cv2

    from .frontend.image import to_uint8
    from .frontend.interpolation import valid_pixels
    from .geometry import from_latlon

    img = np.asarray(image)
    if img.shape[:2] != (camera.height, camera.width):
        raise ValueError(f"the image is {img.shape[:2]} (H, W), the camera's "
                         f"{(camera.height, camera.width)}: give the image the camera took")
    img = to_uint8(img)
    out = np.ascontiguousarray(np.repeat(img[..., None], 3, -1) if img.ndim == 2 else img[..., :3])
    scale = max(1, round(512 / max(camera.width, camera.height)))  # small images: enlarged
    if scale != 1:
        out = cv2.resize(out, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    half = np.radians(np.linspace(-90.0, 90.0, 361))
    for lon in np.arange(-180.0, 180.0, step):
        _draw_curve(out, camera, from_latlon(half, np.full_like(half, np.radians(lon))),
                    GRATICULE, 1, scale)
    t = np.radians(np.linspace(-180.0, 180.0, 721))
    lats = np.arange(-90.0 + step, 90.0, step)
    for lat in sorted(lats, key=lambda a: a == 0):  # the horizon last, on top
        _draw_curve(out, camera, from_latlon(np.full_like(t, np.radians(lat)), t),
                    HORIZON if lat == 0 else GRATICULE, 2 if lat == 0 else 1, scale)
    uv, seen = camera.sees(np.array([[1.0, 0.0, 0.0]]))
    if seen[0]:
        u, v = (uv[0] + 0.5) * scale - 0.5
        cv2.putText(out, "0", (int(u) + 4, int(v) - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.5, HORIZON, 1,
                    cv2.LINE_AA)
    valid = valid_pixels(camera).astype(np.uint8)
    if not valid.all():
        if scale != 1:
            valid = cv2.resize(valid, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
        edges, _ = cv2.findContours(valid, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(out, edges, -1, VIEW_EDGE, 2)
    return out


def contact_sheet(rows, path=None, titles=None, legend=None):
    """A figure of rendered views: ``rows`` is a list (one per scene) of lists of
    ``(title, image)`` pairs; images of one row share a height. ``legend``: ``{name: RGB
    uint8}`` drawn below (e.g. the label palette)."""
    rows = [list(r) for r in rows]
    ncol = max(len(r) for r in rows)
    ratios = [im.shape[1] / im.shape[0] for _, im in rows[0]]
    fig, axes = plt.subplots(len(rows), ncol, figsize=(2.2 * sum(ratios), 2.4 * len(rows)),
                             gridspec_kw={"width_ratios": ratios}, squeeze=False)
    for i, row in enumerate(rows):
        for j, (title, im) in enumerate(row):
            axes[i, j].imshow(im, interpolation="lanczos")
            axes[i, j].set_title(title if titles is None else f"{titles[i]}: {title}", fontsize=8)
            axes[i, j].axis("off")
    rect = None
    if legend:
        from matplotlib.patches import Patch

        # as many entries a line as the figure's width holds (about 1.1 inch each)
        ncol = max(1, min(len(legend), int(fig.get_figwidth() / 1.1)))
        lines = -(-len(legend) // ncol)
        fig.legend(handles=[Patch(color=np.asarray(c) / 255, label=n) for n, c in legend.items()],
                   loc="lower center", ncol=ncol, fontsize=8, frameon=False)
        rect = (0, min(0.5, 0.2 * lines / fig.get_figheight()), 1, 1)
    return _finish(fig, path, rect=rect)


def view_panels(view, camera, name: str) -> list:
    """``[(title, RGB with boxes), (title, labels in the palette)]`` of a rendered view."""
    from .scenes import DETECTION_CLASSES, colourize

    rgb = draw_boxes(view.rgb, camera, view.boxes, [DETECTION_CLASSES[c] for c in view.box_class])
    return [(f"{name}: RGB + boxes", rgb), (f"{name}: labels", colourize(view.label))]


def plot_detections(sets: dict, preds: dict, path=None, samples=(0, 1), min_score: float = 0.3,
                    ignored: dict | None = None):
    """The detection protocol's figure: for a few test views, the true boxes (green) and
    the detections scoring at least ``min_score`` (yellow, named) on the panorama, the
    rotated panorama, the fisheye and the pinhole image (and any other test set, titled
    by its key). ``sets``/``preds``: protocol key -> dataset / list of detections (see
    :mod:`usf_graph.train.det`); ``ignored``: protocol key -> bool ``[K]`` over the
    split's true boxes, those that scoring ignores because the camera cuts them (drawn
    red)."""
    from .scenes import DETECTION_CLASSES

    titles = {"a": "panorama", "b": "rotated", "c": "fisheye 190", "d": "pinhole 90"}
    rows = []
    for i in samples:
        row = []
        for key in sets:
            if key not in preds:  # the training split
                continue
            title = titles.get(key, key)
            ds, det = sets[key], preds[key][i]
            a, b = int(ds.box_ptr[i]), int(ds.box_ptr[i + 1])
            cut = np.zeros(b - a, bool) if ignored is None else np.asarray(ignored[key][a:b], bool)
            img = draw_boxes(ds.image[i].numpy(), ds.camera, ds.boxes[a:b][~cut], colour=TRUTH,
                             thickness=1)
            img = draw_boxes(img, ds.camera, ds.boxes[a:b][cut], colour=CUT, thickness=1)
            keep = det["scores"] >= min_score
            img = draw_boxes(img, ds.camera, det["boxes"][keep],
                             [DETECTION_CLASSES[c] for c in det["classes"][keep]], thickness=1)
            row.append((title, img))
        rows.append(row)
    legend = {"truth": TRUTH, f"detections (score >= {min_score:g})": DETECTION}
    if ignored is not None:
        legend["truth the camera cuts (ignored in scoring)"] = CUT
    return contact_sheet(rows, path, titles=[f"test view {i}" for i in samples], legend=legend)


def plot_segmentation(sets: dict, preds: dict, path=None, sample: int = 0):
    """The segmentation protocol's figure: for one test view per protocol (rows), the
    camera's image, the true labels and each model's prediction in the camera's pixels
    (pixels the camera does not see are black). ``sets``: protocol key -> dataset;
    ``preds``: model name -> protocol key -> ``[S, H, W]`` labels (see
    :mod:`usf_graph.train.seg`)."""
    from .scenes import PALETTE, SEMANTIC_CLASSES, colourize

    keys = [k for k in sets if k != "train" and all(k in p for p in preds.values())]
    rows = []
    for k in keys:
        ds = sets[k]
        seen = ds.label_image[sample].numpy() != 255
        row = [(f"({k}) image", ds.image[sample].numpy()),
               (f"({k}) truth", colourize(ds.label_image[sample].numpy()))]
        for name, p in preds.items():
            row.append((f"({k}) {name}", colourize(np.where(seen, p[k][sample], 255))))
        rows.append(row)
    return contact_sheet(rows, path, legend=dict(zip(SEMANTIC_CLASSES, PALETTE)))


class FrameVideo:
    """Pictures (RGB uint8 ``[H, W, 3]``) written to a video as they come, each resized to
    the first one's size: ``.avi`` as Motion JPEG, ``.mp4`` as MPEG-4 part 2 (what OpenCV's
    wheels write without extra codecs)."""

    CODECS = {".avi": "MJPG", ".mp4": "mp4v"}

    def __init__(self, path, fps: float = 10.0):
        self.path = Path(path)
        if self.path.suffix.lower() not in self.CODECS:
            raise ValueError(f"video {self.path}: write .avi or .mp4")
        if not fps > 0:
            raise ValueError(f"video frame rate must be positive, got {fps}")
        self.fps, self.size, self.frames, self._writer = float(fps), None, 0, None

    def add(self, rgb: np.ndarray) -> None:
        """Appends one RGB picture ``[H, W, 3]`` uint8 (the first sets the video's size)."""
        import cv2

        rgb = np.ascontiguousarray(rgb)
        if self._writer is None:
            h, w = rgb.shape[:2]
            self.size = (w + w % 2, h + h % 2)  # codecs want even sizes
            if self.size != (w, h):
                print(f"{self.path.name}: frames of {w}x{h} resized to {self.size[0]}x"
                      f"{self.size[1]}, since video codecs want even sizes")
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._writer = cv2.VideoWriter(str(self.path), cv2.VideoWriter_fourcc(
                *self.CODECS[self.path.suffix.lower()]), self.fps, self.size)
            if not self._writer.isOpened():
                raise ValueError(f"OpenCV cannot write {self.path} here; try .avi")
        if rgb.shape[1::-1] != self.size:
            rgb = cv2.resize(rgb, self.size, interpolation=cv2.INTER_AREA)
        self._writer.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        self.frames += 1

    def close(self) -> None:
        """Finishes the file; call it when the last picture is added."""
        if self._writer is not None:
            self._writer.release()
            self._writer = None
