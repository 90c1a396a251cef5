"""Files: a JPEG panorama marked as a 360 photo, as another reader (Pillow) sees it; a
photo's EXIF orientation, and images read as their sensor stored them."""

import xml.etree.ElementTree as ET

import cv2
import numpy as np
import pytest
from PIL import Image

from usf_graph.cli import main
from usf_graph.fileio import (
    XMP_ID,
    atomic_write,
    exif_orientation,
    load_refusal,
    mark_360_photo,
    read_photo_sphere,
    write_image,
)

GPANO = "{http://ns.google.com/photos/1.0/panorama/}"


def _gpano(path) -> dict:
    """The GPano attributes of the XMP that Pillow finds in the JPEG ``path``."""
    with Image.open(path) as im:
        xmp = im.info.get("xmp")
    if xmp is None:
        return {}
    desc = ET.fromstring(xmp).find(".//{http://www.w3.org/1999/02/22-rdf-syntax-ns#}Description")
    return {k[len(GPANO):]: v for k, v in desc.attrib.items() if k.startswith(GPANO)}


def test_mark_360_photo_writes_gpano_that_another_reader_finds(tmp_path):
    """Pillow reads the Photo Sphere XMP (the whole panorama: cropped area = full size) from
    the segment after JFIF; the pixels decode as before; marking again replaces the mark."""
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(0, 256, (90, 180, 3)).astype(np.uint8), (5, 5), 2)
    path = tmp_path / "pano.jpg"
    cv2.imwrite(str(path), img)
    before = cv2.imread(str(path))
    assert _gpano(path) == {}
    mark_360_photo(path)
    got = _gpano(path)
    assert got["ProjectionType"] == "equirectangular" and got["UsePanoramaViewer"] == "True"
    assert (got["FullPanoWidthPixels"], got["FullPanoHeightPixels"]) == ("180", "90")
    assert (got["CroppedAreaImageWidthPixels"], got["CroppedAreaImageHeightPixels"]) == ("180", "90")
    assert got["CroppedAreaLeftPixels"] == got["CroppedAreaTopPixels"] == "0"
    assert np.array_equal(cv2.imread(str(path)), before)
    data = path.read_bytes()
    assert data[2:4] == b"\xff\xe0" and data.index(XMP_ID) > data.index(b"JFIF")  # after JFIF
    mark_360_photo(path, software="again")
    assert path.read_bytes().count(XMP_ID) == 1 and _gpano(path)["StitchingSoftware"] == "again"


def test_mark_360_photo_refuses_what_is_no_jpeg_and_keeps_it(tmp_path):
    png = tmp_path / "pano.png"
    cv2.imwrite(str(png), np.zeros((8, 16, 3), np.uint8))
    data = png.read_bytes()
    with pytest.raises(ValueError, match="is not a JPEG"):
        mark_360_photo(png)
    jpg = tmp_path / "cut.jpg"
    cv2.imwrite(str(jpg), np.zeros((8, 16, 3), np.uint8))
    cut = jpg.read_bytes()[:10]  # inside the JFIF segment
    jpg.write_bytes(cut)
    with pytest.raises(ValueError, match="runs past the file's end"):
        mark_360_photo(jpg)
    assert png.read_bytes() == data and jpg.read_bytes() == cut


def _photo_sphere_xmp(fields: dict, as_elements: bool) -> bytes:
    """An XMP packet with GPano ``fields``, as attributes or as elements (cameras write
    both forms)."""
    ns = 'xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#" xmlns:GPano="http://ns.google.com/photos/1.0/panorama/"'
    if as_elements:
        body = "".join(f"<GPano:{k}>{v}</GPano:{k}>" for k, v in fields.items())
        desc = f'<rdf:Description rdf:about="">{body}</rdf:Description>'
    else:
        desc = '<rdf:Description rdf:about="" ' + " ".join(f'GPano:{k}="{v}"' for k, v in fields.items()) + "/>"
    return f'<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF {ns}>{desc}</rdf:RDF></x:xmpmeta>'.encode()


@pytest.mark.parametrize("as_elements", [False, True], ids=["attributes", "elements"])
def test_read_photo_sphere_reads_what_pillow_wrote(tmp_path, as_elements):
    fields = {"ProjectionType": "equirectangular", "FullPanoWidthPixels": "720",
              "CroppedAreaTopPixels": "60"}
    path = tmp_path / "sphere.jpg"
    Image.fromarray(np.zeros((8, 16, 3), np.uint8)).save(path, xmp=_photo_sphere_xmp(fields, as_elements))
    assert read_photo_sphere(path) == fields
    data = path.read_bytes()  # SOI, JFIF (APP0), XMP (APP1), ...
    assert data[2:4] == b"\xff\xe0"
    jfif_end = 4 + int.from_bytes(data[4:6], "big")
    comment = b"\xff\xfe" + (2 + 13).to_bytes(2, "big") + b"from a camera"
    noted = tmp_path / "noted.jpg"  # a comment segment between JFIF and the XMP
    noted.write_bytes(data[:jfif_end] + comment + data[jfif_end:])
    assert read_photo_sphere(noted) == fields
    Image.fromarray(np.zeros((8, 16, 3), np.uint8)).save(tmp_path / "plain.jpg")
    Image.fromarray(np.zeros((8, 16, 3), np.uint8)).save(tmp_path / "bad.jpg", xmp=b"<x:xmpmeta")
    cv2.imwrite(str(tmp_path / "p.png"), np.zeros((8, 16, 3), np.uint8))
    for name in ("plain.jpg", "bad.jpg", "p.png"):  # none, not well-formed, no JPEG
        assert read_photo_sphere(tmp_path / name) is None
    mark_360_photo(tmp_path / "plain.jpg")  # and what we write
    assert read_photo_sphere(tmp_path / "plain.jpg")["FullPanoWidthPixels"] == "16"


def _tagged_jpeg(path, pixels, orientation):
    exif = Image.Exif()
    exif[0x0112] = orientation
    Image.fromarray(pixels).save(path, quality=100, subsampling=0, exif=exif.tobytes())


def test_exif_orientation_reads_the_tag_pillow_wrote(tmp_path):
    pixels = np.zeros((8, 12, 3), np.uint8)
    for k in range(1, 9):
        _tagged_jpeg(tmp_path / f"{k}.jpg", pixels, k)
        assert exif_orientation(tmp_path / f"{k}.jpg") == k
    Image.fromarray(pixels).save(tmp_path / "plain.png")
    (tmp_path / "empty.jpg").write_bytes(b"")
    (tmp_path / "text.jpg").write_text("not an image")
    for k in (0, 9):  # outside the eight the standard defines
        _tagged_jpeg(tmp_path / f"{k}.jpg", pixels, k)
    for name in ("plain.png", "empty.jpg", "text.jpg", "0.jpg", "9.jpg"):
        assert exif_orientation(tmp_path / name) is None


def test_atomic_write_makes_the_folders_and_leaves_nothing_when_writing_fails(tmp_path):
    path = tmp_path / "a" / "b" / "out.bin"
    atomic_write(path, lambda f: f.write(b"new"))
    assert path.read_bytes() == b"new"

    def fail(f):
        f.write(b"half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        atomic_write(path, fail)
    assert path.read_bytes() == b"new" and sorted(p.name for p in path.parent.iterdir()) == ["out.bin"]


def test_load_refusal_keeps_the_reason_and_drops_the_advice():
    unpickler = RuntimeError("Weights only load failed. ... WeightsUnpickler error: Unsupported "
                             "global: GLOBAL os.system  \nCheck the documentation")
    assert load_refusal(unpickler) == "Unsupported global: GLOBAL os.system"
    assert load_refusal(ValueError("bad header. Re-run with more")) == "bad header"
    assert load_refusal(EOFError()) == "EOFError"


def test_an_image_is_read_as_stored_whatever_viewers_turn_and_the_user_is_told(tmp_path, capsys):
    """A 24x16 image tagged "turn 90 degrees clockwise": OpenCV's default reading turns it
    to 16x24 (the trap), ``read_image`` keeps the sensor's 24x16 pixels, RGB, and says so."""
    from usf_graph.cli_inputs import read_image

    rng = np.random.default_rng(0)
    pixels = np.repeat(np.repeat(rng.integers(0, 256, (2, 3, 3), dtype=np.uint8), 8, 0), 8, 1)
    _tagged_jpeg(tmp_path / "phone.jpg", pixels, 6)
    assert cv2.imread(str(tmp_path / "phone.jpg")).shape == (24, 16, 3)  # turned for display
    got = read_image(tmp_path / "phone.jpg")
    assert got.shape == (16, 24, 3) and np.abs(got.astype(int) - pixels).max() <= 4  # JPEG's loss
    said = capsys.readouterr().out
    assert "phone.jpg is shown turned 90 degrees clockwise by viewers" in said
    assert "PIL.ImageOps.exif_transpose" in said
    _tagged_jpeg(tmp_path / "upright.jpg", pixels, 1)
    assert read_image(tmp_path / "upright.jpg").shape == (16, 24, 3)
    assert capsys.readouterr().out == ""


def test_write_image_writes_what_opencv_reads_and_refuses_what_it_cannot(tmp_path, capsys):
    img = np.random.default_rng(0).integers(0, 256, (12, 20, 3), dtype=np.uint8)
    write_image(tmp_path / "a" / "img.png", img)  # its folder made
    assert np.array_equal(cv2.imread(str(tmp_path / "a" / "img.png")), img)
    labels = np.arange(240, dtype=np.uint8).reshape(12, 20)
    write_image(tmp_path / "labels.png", labels)
    assert np.array_equal(cv2.imread(str(tmp_path / "labels.png"), cv2.IMREAD_UNCHANGED), labels)
    for name in ("img.xyz", "img"):  # no writer for either suffix
        with pytest.raises(ValueError, match=f"cannot write .*{name}: use an image suffix"):
            write_image(tmp_path / name, img)
        assert not (tmp_path / name).exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temp file
    cv2.imwrite(str(tmp_path / "pano.png"), np.zeros((16, 32, 3), np.uint8))
    assert main(["render", str(tmp_path / "pano.png"), "--camera", "equirectangular", "--to",
                 "equirectangular:32x16", "--out", str(tmp_path / "out.xyz")]) == 2
    assert "use an image suffix OpenCV knows" in capsys.readouterr().err


def test_mark_360_photo_keeps_the_exif_segment(tmp_path):
    """Exif is an APP1 segment as XMP is; only the XMP one is replaced."""
    path = tmp_path / "turned.jpg"
    _tagged_jpeg(path, np.zeros((8, 16, 3), np.uint8), 6)
    mark_360_photo(path)
    assert exif_orientation(path) == 6 and path.read_bytes().count(XMP_ID) == 1
