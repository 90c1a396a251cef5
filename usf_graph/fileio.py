"""Files: atomic writes (a temp file in the target's folder, then ``os.replace``),
checksums, downloads, image encoding and decoding, and a JPEG panorama marked as a 360
photo.

Readers never see a partial file, concurrent writers of one path each leave a complete
one, and a failed write removes its temp file.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO


def atomic_write(path, write: Callable[[IO], None], mode: str = "wb") -> None:
    """Create ``path``'s folder, call ``write(f)`` on a temp file opened with ``mode``, and
    move it onto ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, mode) as f:
            write(f)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_torch_save(obj, path) -> None:
    """``torch.save(obj, path)``, atomically."""
    import torch

    atomic_write(path, lambda f: torch.save(obj, f))


def load_refusal(e: Exception) -> str:
    """One line of why ``torch.load(..., weights_only=True)`` refused a file: the unpickler's
    own reason, without torch's advice to load it with ``weights_only=False``, which runs
    whatever the file holds."""
    import re

    why = re.search(r"WeightsUnpickler error:\s*(.+)", str(e))
    if why:
        return why.group(1).strip()
    return (str(e).splitlines() or [type(e).__name__])[0].split(". ")[0][:200]


def write_image(path, image, params: tuple = ()) -> None:
    """``cv2.imwrite(path, image, params)`` (BGR; ``params``: e.g. a JPEG's quality),
    atomically, and loud where OpenCV is not: a suffix it has no writer for, or a failed
    write, raises ``ValueError`` naming the file."""
    import cv2

    path = Path(path)
    try:
        ok, data = cv2.imencode(path.suffix, image, list(params))
    except cv2.error:  # OpenCV 5 raises for a suffix it has no writer for
        ok = False
    if not ok:
        raise ValueError(f"cannot write {path}: use an image suffix OpenCV knows (.png, .jpg)")
    atomic_write(path, lambda f: f.write(data.tobytes()))


def decode_image(path, flags: int | None = None):
    """The image in file ``path`` (or in its bytes, already read) as OpenCV decodes it
    (``flags``: default ``IMREAD_UNCHANGED``), or None when the file is empty or not an
    image OpenCV reads. Decoded from memory: unlike ``cv2.imread``, nothing is printed on
    stderr, and any path the OS accepts works. A missing file raises ``FileNotFoundError``."""
    import cv2
    import numpy as np

    data = np.frombuffer(path, np.uint8) if isinstance(path, bytes) else np.fromfile(Path(path), np.uint8)
    flags = cv2.IMREAD_UNCHANGED if flags is None else flags
    return cv2.imdecode(data, flags) if data.size else None


EXIF_ORIENTATIONS = {2: "mirrored left to right", 3: "turned 180 degrees",
                     4: "mirrored top to bottom", 5: "mirrored along its main diagonal",
                     6: "turned 90 degrees clockwise", 7: "mirrored along its other diagonal",
                     8: "turned 90 degrees counterclockwise"}


def exif_orientation(path) -> int | None:
    """The EXIF Orientation tag (1 to 8) of the image file ``path`` (or of its bytes,
    already read): how viewers turn or mirror its stored pixels for display; None where it
    has none or is no file Pillow reads. Only the header is parsed."""
    import io

    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(path) if isinstance(path, bytes) else path) as im:
            k = im.getexif().get(0x0112)
    except (OSError, UnidentifiedImageError, ValueError):
        return None
    return int(k) if isinstance(k, int) and 1 <= k <= 8 else None


def file_md5(path) -> str:
    h = hashlib.md5()  # noqa: S324 - a checksum the data publishers give, not security
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def download(url: str, path, md5: str | None = None, progress: bool = True) -> Path:
    """Fetch ``url`` to ``path`` atomically, with a progress bar and an MD5 check.

    An existing ``path`` with the right checksum is kept. A failed or corrupt download
    leaves nothing behind and raises ``FileNotFoundError`` (unreachable) or
    ``ValueError`` (wrong checksum), naming the file and the manual fix.
    """
    import urllib.error
    import urllib.request

    from tqdm.auto import tqdm

    path = Path(path)
    if path.exists() and (md5 is None or file_md5(path) == md5):
        return path

    def write(f):
        h = hashlib.md5()  # noqa: S324
        with urllib.request.urlopen(url, timeout=60) as r:
            total = int(r.headers.get("Content-Length") or 0) or None
            with tqdm(total=total, unit="B", unit_scale=True, desc=path.name,
                      disable=not progress) as bar:
                for block in iter(lambda: r.read(1 << 20), b""):
                    f.write(block)
                    h.update(block)
                    bar.update(len(block))
        if md5 is not None and h.hexdigest() != md5:
            raise ValueError(f"{url}: MD5 {h.hexdigest()} but expected {md5}; the download is "
                             f"corrupt or the mirror changed. Retry, or put a good copy at {path}.")

    try:
        atomic_write(path, write)
    except (urllib.error.URLError, TimeoutError, ConnectionError) as e:
        raise FileNotFoundError(f"could not download {url} ({getattr(e, 'reason', e)}). "
                                f"Download it by hand and put it at {path}.") from None
    return path


#: A JPEG's XMP segment (APP1) begins with this name.
XMP_ID = b"http://ns.adobe.com/xap/1.0/\0"
_GPANO = (
    '<?xpacket begin="\ufeff" id="W5M0MpCehiHzreSzNTczkc9d"?>'
    '<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF '
    'xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#"><rdf:Description rdf:about="" '
    'xmlns:GPano="http://ns.google.com/photos/1.0/panorama/" '
    'GPano:ProjectionType="equirectangular" GPano:UsePanoramaViewer="True" '
    'GPano:CroppedAreaImageWidthPixels="{w}" GPano:CroppedAreaImageHeightPixels="{h}" '
    'GPano:FullPanoWidthPixels="{w}" GPano:FullPanoHeightPixels="{h}" '
    'GPano:CroppedAreaLeftPixels="0" GPano:CroppedAreaTopPixels="0" '
    'GPano:StitchingSoftware="{software}"/></rdf:RDF></x:xmpmeta><?xpacket end="w"?>')


def mark_360_photo(path, software: str = "usf-graph") -> None:
    """Marks the JPEG ``path``, a whole equirectangular panorama, as a 360 photo: Google's
    Photo Sphere XMP metadata (GPano), which Google Photos, Facebook and other 360 viewers
    read. It goes after the file's leading application segments (JFIF, Exif); an XMP segment
    already there is replaced. The file is rewritten atomically; the pixels are not touched."""
    path = Path(path)
    data = path.read_bytes()
    if data[:2] != b"\xff\xd8":
        raise ValueError(f"{path} is not a JPEG: 360 photo metadata goes into a .jpg")
    segments, i = _leading_segments(data, path)
    kept = [data[a:b] for a, b in segments if not _is_xmp(data, a)]
    image = decode_image(data)
    if image is None:
        raise ValueError(f"{path}: OpenCV cannot decode this JPEG: the file is corrupt")
    h, w = image.shape[:2]
    xmp = XMP_ID + _GPANO.format(w=w, h=h, software=software).encode()
    segment = b"\xff\xe1" + (len(xmp) + 2).to_bytes(2, "big") + xmp
    atomic_write(path, lambda f: f.write(b"".join([data[:2], *kept, segment, data[i:]])))


_GPANO_NS = "http://ns.google.com/photos/1.0/panorama/"


def read_photo_sphere(path) -> dict | None:
    """The Photo Sphere (GPano) fields of the XMP in the JPEG ``path``, as strings by name
    (``ProjectionType``, ``FullPanoWidthPixels``, ``CroppedAreaLeftPixels``, ...), whether
    written as attributes or as elements; None where the file is no JPEG or has none."""
    data = Path(path).read_bytes()
    if data[:2] != b"\xff\xd8":
        return None
    found = {}
    for a, b in _leading_segments(data, path)[0]:
        if _is_xmp(data, a):  # one not well-formed gives no fields
            found.update(xml_fields(data[a + 4 + len(XMP_ID):b].strip(b"\0 \n"), _GPANO_NS) or {})
    return found or None


def xml_fields(xml: bytes, namespace: str) -> dict | None:
    """The fields of ``namespace`` in the XML ``xml``, as strings by name: its attributes
    and its elements' text alike (XMP writes either); None where ``xml`` is not well-formed."""
    import xml.etree.ElementTree as ET

    try:
        root = ET.fromstring(xml)
    except ET.ParseError:
        return None
    ns, found = "{" + namespace + "}", {}
    for el in root.iter():
        found.update({k[len(ns):]: v for k, v in el.attrib.items() if k.startswith(ns)})
        if el.tag.startswith(ns) and el.text and el.text.strip():
            found[el.tag[len(ns):]] = el.text.strip()
    return found


def _leading_segments(data: bytes, path) -> tuple[list, int]:
    """A JPEG's application and comment segments right after its start, ``[(start, end)]``,
    and the byte where they end."""
    i, out = 2, []
    while i + 4 <= len(data) and data[i] == 0xFF and (0xE0 <= data[i + 1] <= 0xEF or data[i + 1] == 0xFE):
        end = i + 2 + int.from_bytes(data[i + 2:i + 4], "big")
        if end > len(data):
            raise ValueError(f"{path}: a JPEG segment runs past the file's end: the file is corrupt")
        out.append((i, end))
        i = end
    return out, i


def _is_xmp(data: bytes, start: int) -> bool:
    return data[start + 1] == 0xE1 and data[start + 4:start + 4 + len(XMP_ID)] == XMP_ID
