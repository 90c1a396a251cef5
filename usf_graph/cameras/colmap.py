"""COLMAP's camera lists: ``cameras.txt`` and ``cameras.bin``, alone or in a sparse model's
folder (``sparse/0``).

COLMAP puts the centre of the top-left pixel at (0.5, 0.5); OpenCV and usf-graph put it at
(0, 0). The principal point is shifted by half a pixel on reading, so that a COLMAP
camera and its usf-graph model map every ray to the same pixel of the image.

Models with a closed form here (the rest of COLMAP's list, THIN_PRISM_FISHEYE and
RAD_TAN_THIN_PRISM_FISHEYE, are read through ``pycolmap`` as a measured ray table):

- SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV: :class:`Pinhole`
  with OpenCV's distortion;
- SIMPLE_FISHEYE, FISHEYE, SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE, OPENCV_FISHEYE:
  :class:`KannalaBrandt`, theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8);
- SIMPLE_DIVISION, DIVISION: :class:`Division`; FOV: :class:`FOV`; EUCM: :class:`EUCM`; EQUIRECTANGULAR: :class:`Equirectangular`
  (forward at the image's centre, as in COLMAP).
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from ..geometry import rotation_from_quaternion
from .base import Camera
from .files import Src, plain_list
from .fisheye import FOV, Fisheye, KannalaBrandt
from .omni import EUCM, Mei
from .panorama import Equirectangular, LensNormalMap
from .pinhole import Division, Pinhole
from .rig import mount

# COLMAP's model ids, names and parameter counts (src/colmap/sensor/models.h).
MODELS = {0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4),
          3: ("RADIAL", 5), 4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12),
          7: ("FOV", 5), 8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5),
          10: ("THIN_PRISM_FISHEYE", 12), 11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
          12: ("SIMPLE_DIVISION", 4), 13: ("DIVISION", 5), 14: ("SIMPLE_FISHEYE", 3),
          15: ("FISHEYE", 4), 16: ("EUCM", 6), 17: ("EQUIRECTANGULAR", 2)}
_COUNTS = {name: n for name, n in MODELS.values()}
_PINHOLES = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")
_FISHEYES = ("SIMPLE_FISHEYE", "FISHEYE", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE",
             "OPENCV_FISHEYE")
CLOSED_FORM = _PINHOLES + _FISHEYES + ("SIMPLE_DIVISION", "DIVISION", "FOV", "EUCM",
                                       "EQUIRECTANGULAR")
HALF_PIXEL = 0.5  # COLMAP's pixel centres sit half a pixel right of and below OpenCV's


class CameraList(dict):
    """COLMAP's cameras of one file, by id: ``{id: (model name, width, height, params)}``."""

    def __init__(self, path: Path, entries: dict):
        super().__init__(entries)
        self.path = path

    def pick(self, key) -> Camera:
        """The camera whose COLMAP id is ``key`` (``None``: the only one)."""
        ids = sorted(self)
        if not ids:
            raise ValueError(f"{self.path}: the COLMAP camera list is empty")
        if key is None:
            if len(ids) > 1:
                raise ValueError(f"{self.path}: {len(ids)} COLMAP cameras (ids {_ids(ids)}); "
                                 "choose one with key= (--key on the command line), or list "
                                 "them with cameras.load_all (usf-graph camera --all)")
            key = ids[0]
        try:
            cid = int(key)
        except (TypeError, ValueError):
            cid = None
        if cid not in self:
            raise ValueError(f"{self.path}: no COLMAP camera {key!r} (ids {_ids(ids)}); "
                             "choose one with key= (--key on the command line)")
        model, w, h, params = self[cid]
        return colmap_camera(Src(self.path, f"camera {cid}"), model, w, h, params)


def _ids(ids: list) -> str:
    return ", ".join(map(str, ids[:8])) + (f", ... ({len(ids)} in all)" if len(ids) > 8 else "")


def _rows(text: str):
    """``(line number, tokens)`` of the lines of a COLMAP text file that hold data."""
    for n, line in enumerate(text.splitlines(), 1):
        if line.strip() and not line.lstrip().startswith("#"):
            yield n, line.split()


def is_colmap_text(text: str) -> bool:
    """True for COLMAP's ``cameras.txt``: its header, or a first row ``ID MODEL W H ...``
    with a model COLMAP knows."""
    if "# Camera list" in text[:200]:
        return True
    first = next(_rows(text), (0, []))[1]
    return len(first) >= 4 and first[1] in _COUNTS and first[0].isdigit()


def read_text(path: Path, text: str) -> CameraList:
    cams = {}
    for n, tok in _rows(text):
        where, line = f"{path}, line {n}", " ".join(tok)
        if len(tok) < 4:
            raise ValueError(f"{where}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...', "
                             f"got {line!r}")
        try:
            cid, w, h = int(tok[0]), int(tok[2]), int(tok[3])
            params = [float(t) for t in tok[4:]]
        except ValueError:
            raise ValueError(f"{where}: the id, size and parameters must be numbers, got "
                             f"{line!r}") from None
        if tok[1] not in _COUNTS:
            raise ValueError(f"{where}: unknown COLMAP camera model {tok[1]!r}; COLMAP's "
                             f"models: {', '.join(_COUNTS)}")
        if cid in cams:
            raise ValueError(f"{where}: camera id {cid} appears twice")
        cams[cid] = _entry(where, tok[1], w, h, params)
    return CameraList(path, cams)


def read_binary(path: Path, data: bytes) -> CameraList | None:
    """COLMAP's ``cameras.bin`` (little-endian: uint64 count; per camera uint32 id, int32
    model, uint64 width, uint64 height, float64 params), or None when ``data`` is not one."""
    if len(data) < 8:
        return None
    (count,), at, cams = struct.unpack_from("<Q", data), 8, {}
    for _ in range(count):
        if at + 24 > len(data):
            return None
        cid, mid, w, h = struct.unpack_from("<IiQQ", data, at)
        if mid not in MODELS:
            return None
        name, n = MODELS[mid]
        if at + 24 + 8 * n > len(data):
            return None
        params = list(struct.unpack_from(f"<{n}d", data, at + 24))
        at += 24 + 8 * n
        cams[cid] = _entry(f"{path}, camera {cid}", name, w, h, params)
    return CameraList(path, cams) if at == len(data) else None


def _entry(where: str, name: str, w: int, h: int, params: list) -> tuple:
    if len(params) != _COUNTS[name]:
        raise ValueError(f"{where}: COLMAP's {name} has {_COUNTS[name]} parameters, got "
                         f"{len(params)}: {plain_list(params)}")
    return name, w, h, np.asarray(params, np.float64)


def colmap_camera(src: Src, model: str, w: int, h: int, p: np.ndarray) -> Camera:
    """One COLMAP camera as a usf-graph model, its principal point moved to OpenCV's pixel
    centres (:data:`HALF_PIXEL`)."""
    if model == "EQUIRECTANGULAR":
        if tuple(p) != (w, h):
            raise src.error(f"EQUIRECTANGULAR's parameters {plain_list(p)} must equal its "
                            f"image size [{w}, {h}]")
        return src.build(Equirectangular, width=w, height=h)
    if model in CLOSED_FORM:
        one_f = model.startswith("SIMPLE") or model in ("RADIAL", "RADIAL_FISHEYE")
        f = (p[0], p[0]) if one_f else (p[0], p[1])
        c, rest = (p[1:3], p[3:]) if one_f else (p[2:4], p[4:])
        K = dict(fx=f[0], fy=f[1], cx=c[0] - HALF_PIXEL, cy=c[1] - HALF_PIXEL, width=w, height=h)
        if model == "EUCM":
            return src.build(EUCM, **K, alpha=rest[0], beta=rest[1])
        if model.endswith("DIVISION"):
            return src.build(Division, **K, k=rest[0])
        if model == "FOV":  # omega 0 is COLMAP's undistorted limit
            return src.build(FOV, **K, omega=rest[0]) if rest[0] else src.build(Pinhole, **K)
        if model in _FISHEYES:
            return src.build(KannalaBrandt, **K, k=np.pad(rest, (0, 4 - len(rest))))
        return src.build(Pinhole, **K, dist=np.pad(rest, (0, max(0, 4 - len(rest)))) if len(rest) else None)
    return _ray_table(src, model, w, h, p)


def _ray_table(src: Src, model: str, w: int, h: int, p: np.ndarray) -> Camera:
    """A model without a closed form here, as the ray of every pixel centre that pycolmap
    computes (a :class:`LensNormalMap`)."""
    try:
        import pycolmap
    except ImportError:
        raise src.error(f"COLMAP's {model} has no closed form in usf-graph (those are "
                        f"{', '.join(CLOSED_FORM)}); install pycolmap (pip install pycolmap) "
                        "to read it as a per-pixel ray table") from None
    cam = pycolmap.Camera.create_from_model_name(1, model, 1.0, int(w), int(h))
    cam.params = p
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    uv = np.stack([u, v], -1).reshape(-1, 2) + HALF_PIXEL
    rays = np.asarray(cam.cam_ray_from_img(uv), np.float64)
    # COLMAP's fisheyes end at 90 degrees: past it pycolmap's ray is mirrored and does not
    # project back to its pixel, so only the pixels it maps both ways keep a ray
    back = np.asarray(cam.img_from_cam(rays), np.float64)
    valid = np.all(np.isfinite(rays), -1) & (np.linalg.norm(back - uv, axis=-1) < 1e-6)
    rays, valid = rays.reshape(h, w, 3), valid.reshape(h, w)
    if not valid.any():
        raise src.error(f"pycolmap gives no pixel of this {model} camera a ray; check its "
                        f"parameters {plain_list(p)}")
    return LensNormalMap(rays, valid, source=f"{src.path} (COLMAP {model}, via pycolmap)")


def read_file(path: Path) -> CameraList | None:
    """``path``'s COLMAP camera list, or None when it is not ``cameras.txt``/``.bin``."""
    raw = path.read_bytes()
    if b"\0" in raw[:64]:
        cams = read_binary(path, raw)
        if cams is None:
            raise ValueError(f"{path}: a binary file, but not COLMAP's cameras.bin (its records "
                             "do not add up to the file's length); pass a calibration file")
        return cams
    text = raw.decode(errors="replace")
    return read_text(path, text) if is_colmap_text(text) else None


def in_folder(path: Path) -> Path:
    """The camera list of a COLMAP sparse model's folder: cameras.bin, else cameras.txt."""
    for name in ("cameras.bin", "cameras.txt"):
        if (path / name).is_file():
            return path / name
    raise FileNotFoundError(f"{path} is a folder without cameras.bin or cameras.txt; pass a "
                            "calibration file, or a COLMAP sparse model's folder (sparse/0)")


def colmap_entry(cam: Camera) -> tuple[str, list[float]]:
    """``cam`` as COLMAP's (model name, parameters), its principal point moved to COLMAP's
    pixel centres; a ValueError for a model COLMAP has no closed form of."""
    k = [cam.fx + 0.0, cam.fy + 0.0, cam.cx + HALF_PIXEL, cam.cy + HALF_PIXEL] \
        if hasattr(cam, "fy") else None
    if isinstance(cam, Equirectangular) and cam.whole_sphere:
        return "EQUIRECTANGULAR", [float(cam.width), float(cam.height)]
    if isinstance(cam, Pinhole) and not np.any(cam.dist[8:]):
        d = cam.dist.tolist()
        if not np.any(cam.dist):
            return "PINHOLE", k
        return ("OPENCV", k + d[:4]) if not np.any(cam.dist[4:8]) else ("FULL_OPENCV", k + d[:8])
    if isinstance(cam, KannalaBrandt):
        return "OPENCV_FISHEYE", k + cam.k.tolist()
    if isinstance(cam, Fisheye) and cam.projection == "equidistant":
        return "SIMPLE_FISHEYE", [cam.f, cam.cx + HALF_PIXEL, cam.cy + HALF_PIXEL]
    if isinstance(cam, EUCM):
        return "EUCM", k + [cam.alpha, cam.beta]
    if isinstance(cam, FOV):
        return "FOV", k + [cam.omega]
    if isinstance(cam, Division):
        return "DIVISION", k + [cam.k]
    if isinstance(cam, Mei) and not np.any(cam.dist) and cam.skew == 0:
        s = 1 + cam.xi  # Mei's gamma (z + xi d) is EUCM's f (alpha d + (1 - alpha) z), beta 1
        return "EUCM", [cam.fx / s, cam.fy / s] + k[2:] + [cam.xi / s, 1.0]
    raise ValueError(f"COLMAP has no model for this {type(cam).__name__} ({cam.model}); it "
                     "takes pinholes with OpenCV's radial and tangential distortion, "
                     "Kannala-Brandt, equidistant and FOV fisheyes, the division model, EUCM (and Mei without "
                     "distortion) and full panoramas. Keep it in usf-graph's YAML (cam.save, "
                     "usf-graph camera --save)")


def save_text(cams: dict, path) -> None:
    """Write ``cams`` (``{camera id: Camera}``) as COLMAP's ``cameras.txt``, atomically.
    COLMAP keeps no field-of-view limit, image mask or mounting: those stay behind."""
    from ..fileio import atomic_write

    rows = []
    for cid, cam in cams.items():
        try:
            model, params = colmap_entry(cam)
        except ValueError as e:
            raise ValueError(f"camera {cid}: {e}") from None
        rows.append(" ".join([str(int(cid)), model, str(cam.width), str(cam.height),
                              *(repr(float(v)) for v in params)]))
    text = ("# Camera list with one line of data per camera:\n"
            "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
            f"# Number of cameras: {len(rows)}\n" + "\n".join(rows) + "\n")
    atomic_write(path, lambda f: f.write(text), mode="w")


# -- rigs (COLMAP 3.12 and later: rigs.txt / rigs.bin next to the camera list) -------------

_SENSORS = {0: "CAMERA", 1: "IMU"}


def rig_file(path: Path) -> Path | None:
    """The rig list of a sparse model's folder, or ``path`` itself when it is one."""
    if path.is_dir():
        return next((path / n for n in ("rigs.bin", "rigs.txt") if (path / n).is_file()), None)
    return path if path.name.startswith("rigs.") else None


_IDENTITY = (1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def read_rigs(path: Path) -> dict:
    """``{rig id: [(camera id, sensor_from_rig (qw, qx, qy, qz, tx, ty, tz) or None), ...]}``,
    the reference camera first (its pose the identity); sensors that are not cameras left
    out."""
    raw = path.read_bytes()
    rigs = _rigs_binary(raw) if b"\0" in raw[:64] else _rigs_text(raw.decode(errors="replace"))
    if rigs is None:
        raise ValueError(f"{path}: not COLMAP's rig list (rigs.txt / rigs.bin); write it with "
                         "COLMAP 3.12 or later, or pass the cameras one by one")
    return rigs


def _rigs_text(text: str) -> dict | None:
    rigs = {}
    for _, tok in _rows(text):
        try:
            rid, n, at = int(tok[0]), int(tok[1]), 4
            members = [(tok[2], int(tok[3]), _IDENTITY)]
            for _ in range(n - 1):
                kind, sid, has = tok[at], int(tok[at + 1]), tok[at + 2] == "1"
                q = tuple(float(v) for v in tok[at + 3:at + 10]) if has else None
                members.append((kind, sid, q))
                at += 10 if has else 3
        except (ValueError, IndexError):
            return None
        if at != len(tok):
            return None
        rigs[rid] = [(sid, q) for kind, sid, q in members if kind == "CAMERA"]
    return rigs


def _rigs_binary(raw: bytes) -> dict | None:
    try:
        (count,), at, rigs = struct.unpack_from("<Q", raw), 8, {}
        for _ in range(count):
            rid, n, kind, sid = struct.unpack_from("<IIiI", raw, at)
            at += 16
            members = [(kind, sid, _IDENTITY)]
            for _ in range(n - 1):
                kind, sid, has = struct.unpack_from("<iIB", raw, at)
                at += 9
                q = None
                if has:
                    q = struct.unpack_from("<7d", raw, at)
                    at += 56
                members.append((kind, sid, q))
            rigs[rid] = [(sid, q) for kind, sid, q in members if _SENSORS.get(kind) == "CAMERA"]
    except struct.error:
        return None
    return rigs if at == len(raw) else None


def colmap_rig(path: Path, key=None) -> dict[str, Camera]:
    """The cameras of one COLMAP rig (``key``: its id; None: the only one), each mounted by
    its ``sensor_from_rig`` pose, the reference camera's frame first, named by their
    camera ids."""
    rigs_path = rig_file(path)
    folder = path if path.is_dir() else path.parent
    if rigs_path is None:
        raise ValueError(f"{path}: no rigs.bin or rigs.txt; a COLMAP model holds a rig from "
                         "COLMAP 3.12 on")
    rigs = read_rigs(rigs_path)
    if key is None and len(rigs) != 1:
        raise ValueError(f"{rigs_path}: {len(rigs)} COLMAP rigs (ids {_ids(sorted(rigs))}); "
                         "choose one with key=")
    rid = next(iter(rigs)) if key is None else int(key) if str(key).isdigit() else key
    if rid not in rigs:
        raise ValueError(f"{rigs_path}: no COLMAP rig {key!r} (ids {_ids(sorted(rigs))})")
    cams = read_file(in_folder(folder))
    if cams is None:
        raise ValueError(f"{in_folder(folder)}: not COLMAP's camera list, which the rig in "
                         f"{rigs_path} needs")
    rig = {}
    for cid, q in rigs[rid]:
        if q is None:
            raise ValueError(f"{rigs_path} [rig {rid}, camera {cid}]: no pose in the rig, so "
                             "its place in the rig is unknown; calibrate the rig in COLMAP")
        R = rotation_from_quaternion(np.array(q[:4]))  # sensor_from_rig, COLMAP's (w, x, y, z)
        pose = np.eye(4)  # rig <- sensor
        pose[:3, :3], pose[:3, 3] = R.T, -R.T @ np.array(q[4:])
        rig[str(cid)] = mount(cams.pick(cid), pose)
    return rig
