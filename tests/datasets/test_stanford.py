"""Stanford 2D-3D-S: label decoding with every ignore case, and the loader on fixtures in
the released layout (tiny PNGs, a short semantic_labels.json)."""

import json

import cv2
import numpy as np
import pytest
import torch

from usf_graph.datasets import Stanford2D3DS
from usf_graph.datasets.stanford import FOLDS, MISSING, decode_semantic, label_table

NAMES = ["<UNK>_0_<UNK>_0_0", "ceiling_1_office_1_0", "wall_2_office_1_1", "stairs_1_office_1_0",
         "chair_3_office_1_2"]
# entry -> expected label: <UNK> and stairs (not one of the 13) are ignored
EXPECTED = {0: 255, 1: 3, 2: 11, 3: 255, 4: 4}


def _rgb(index: int):
    return [(index >> 16) & 255, (index >> 8) & 255, index & 255]


def test_label_table(tmp_path):
    p = tmp_path / "semantic_labels.json"
    p.write_text(json.dumps(NAMES))
    assert label_table(p).tolist() == [EXPECTED[i] for i in range(len(NAMES))]
    p.write_text("{not json")
    with pytest.raises(ValueError, match="semantic_labels.json"):
        label_table(p)
    for wrong in ({"chair": 1}, ["chair_1", 7]):
        p.write_text(json.dumps(wrong))
        with pytest.raises(ValueError, match="must be a JSON list of strings"):
            label_table(p)


def test_decode_every_ignore_case():
    table = np.array([EXPECTED[i] for i in range(len(NAMES))], np.uint8)
    idx = [0, 1, 2, 3, 4, MISSING, len(NAMES), 9815, 65536 + 1]  # 65537: R != 0, past the end
    rgb = np.array([[_rgb(i) for i in idx]], np.uint8)
    out = decode_semantic(rgb, table)
    assert out.tolist() == [[255, 3, 11, 255, 4, 255, 255, 255, 255]]
    # 0x0D0D0D stays ignored even with a list long enough to reach it
    long = np.full(MISSING + 1, 5, np.uint8)
    assert decode_semantic(np.array([[_rgb(MISSING), _rgb(7)]], np.uint8), long).tolist() == [[255, 5]]
    with pytest.raises(ValueError, match="RGB uint8"):
        decode_semantic(np.zeros((2, 2), np.uint8), table)
    # the index is R * 65536 + G * 256 + B: entries reached through G and through R
    big = np.full(70_000, 255, np.uint8)
    big[[3 * 256 + 2, 65536 + 5 * 256 + 7]] = [6, 9]
    got = decode_semantic(np.array([[_rgb(3 * 256 + 2), _rgb(65536 + 5 * 256 + 7), [2, 3, 0]]],
                                   np.uint8), big)
    assert got.tolist() == [[6, 9, 255]]


def _write_pano(root, area, name, W=32, H=16, rgba=False, seed=0):
    """One panorama: vertical bands of entries 0..4, a MISSING block, RGB noise."""
    rng = np.random.default_rng(seed)
    sem = np.zeros((H, W, 3), np.uint8)
    for k in range(5):
        sem[:, k * W // 5:(k + 1) * W // 5] = _rgb(k)
    sem[: H // 4, : W // 4] = _rgb(MISSING)
    rgb = rng.integers(0, 256, (H, W, 4 if rgba else 3), dtype=np.uint8)
    d = root / f"area_{area}" / "pano"
    (d / "rgb").mkdir(parents=True, exist_ok=True)
    (d / "semantic").mkdir(parents=True, exist_ok=True)
    stem = f"camera_{name}_office_1_frame_equirectangular_domain"
    cv2.imwrite(str(d / "rgb" / f"{stem}_rgb.png"), rgb[..., [2, 1, 0, 3][: rgb.shape[-1]]])
    cv2.imwrite(str(d / "semantic" / f"{stem}_semantic.png"), sem[..., ::-1])
    return rgb, sem


@pytest.fixture
def stanford(tmp_path):
    (tmp_path / "semantic_labels.json").write_text(json.dumps(NAMES))
    pics = {"5a": _write_pano(tmp_path, "5a", "aa", rgba=True, seed=1),
            "5b": _write_pano(tmp_path, "5b", "bb", seed=2)}
    return tmp_path, pics


def test_loader_reads_real_layout(stanford):
    root, pics = stanford
    ds = Stanford2D3DS(root, fold=1, split="test", grid="icosahedral:2", size=8, progress=False)
    assert FOLDS[1][1] == ("5a", "5b") and len(ds) == 2
    assert ds.names == ["camera_aa_office_1", "camera_bb_office_1"]
    rgb, sem = pics["5a"]
    # the 2x downsized labels: nearest of the decoded full-size labels
    table = np.array([EXPECTED[i] for i in range(len(NAMES))], np.uint8)
    want = cv2.resize(decode_semantic(sem, table), (16, 8), interpolation=cv2.INTER_NEAREST)
    assert np.array_equal(ds.label_image[0].numpy(), want)
    assert set(np.unique(want)) == {3, 4, 11, 255}
    want_rgb = cv2.resize(rgb[..., :3], (16, 8), interpolation=cv2.INTER_AREA)
    assert np.array_equal(ds.image[0].numpy(), want_rgb)  # alpha dropped, channels in RGB order
    # per-point labels: the label of the pixel each grid point falls in
    uv, _ = ds.camera.project(ds.grid.pos.numpy())
    u = np.clip(np.floor(uv[:, 0] + 0.5).astype(int), 0, 15)
    v = np.clip(np.floor(uv[:, 1] + 0.5).astype(int), 0, 7)
    assert np.array_equal(ds.y[0].numpy(), want[v, u])
    d = ds[1]
    assert d.x.shape == (162, 3) and d.image.shape == (1, 8, 16, 3) and d.mask.all()
    assert torch.allclose(d.x, ds.x[1].float()) and 0 <= d.x.min() and d.x.max() <= 1
    # RGB in [0, 1]: the stored image's values over 255, lifted (stored in half precision)
    want_x = ds.frontend.lift(ds.image[1].numpy().astype(np.float32) / 255)
    assert ds.x.dtype == torch.float16
    torch.testing.assert_close(ds.x[1].float(), want_x.float(), rtol=1e-3, atol=1e-6)
    # processed once: a second instance loads the file
    again = Stanford2D3DS(root, fold=1, split="test", grid="icosahedral:2", size=8, progress=False)
    assert torch.equal(again.y, ds.y)


def test_loader_errors(stanford, tmp_path):
    root, _ = stanford
    with pytest.raises(FileNotFoundError, match=r"^area_1, area_2, area_3, area_4, area_6 not found under .*2D-3D-Semantics"):
        Stanford2D3DS(root, fold=1, split="train", grid="icosahedral:1", size=8, progress=False)
    with pytest.raises(ValueError, match="fold"):
        Stanford2D3DS(root, fold=4, split="test")
    with pytest.raises(ValueError, match="split must be 'train' or 'test', got 'val'"):
        Stanford2D3DS(root, fold=1, split="val")
    with pytest.raises(FileNotFoundError, match="^semantic_labels.json not found under"):
        Stanford2D3DS(tmp_path / "nothing", fold=1, split="test")
    # a corrupt RGB PNG names itself; a missing RGB is reported
    rgb = next((root / "area_5b" / "pano" / "rgb").glob("*.png"))
    rgb.write_bytes(b"\x89PNG broken")
    with pytest.raises(ValueError, match="corrupt"):
        Stanford2D3DS(root, fold=1, split="test", grid="icosahedral:1", size=8, progress=False)
    rgb.unlink()
    with pytest.raises(FileNotFoundError, match=r"_rgb\.png is missing \(its semantic image exists\)"):
        Stanford2D3DS(root, fold=1, split="test", grid="icosahedral:1", size=8, progress=False)


def test_loader_rejects_wrong_size(tmp_path):
    (tmp_path / "semantic_labels.json").write_text(json.dumps(NAMES))
    _write_pano(tmp_path, "5a", "aa", W=30, H=16)
    _write_pano(tmp_path, "5b", "bb")
    with pytest.raises(ValueError, match=r"_rgb\.png is 30x16 and its semantic image 30x16; both "
                                         "must be the same 2:1 equirectangular size"):
        Stanford2D3DS(tmp_path, fold=1, split="test", grid="icosahedral:1", size=8, progress=False)
