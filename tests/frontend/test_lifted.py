"""Lifted samples on disk: what ``save_lifted`` writes comes back from ``load_lifted`` as the
frontend's own image, and every damaged or foreign file is refused with what to do."""

import numpy as np
import pytest
import torch

from usf_graph import cameras, grids
from usf_graph.frontend import SphericalFrontend, load_lifted, read_lifted, save_lifted


@pytest.fixture(scope="module")
def lifted():
    fe = SphericalFrontend(cameras.Fisheye(10.0, 15.5, 15.5, 32, 32, fov_deg=180),
                           grids.icosahedral(2))
    img = np.random.default_rng(0).random((32, 32, 2))
    return fe, fe(img)


def test_a_lifted_sample_comes_back_as_the_frontends_image(tmp_path, lifted):
    fe, ref = lifted
    save_lifted(tmp_path / "s.pt", ref.x, fe, source="img.png")
    back = load_lifted(tmp_path / "s.pt")
    for k in ("x", "mask", "pos", "area", "edge_index", "edge_attr"):
        assert torch.equal(back[k], ref[k]), k
    assert 0 < int(back.mask.sum()) < len(fe.grid)  # a half sphere: both kinds of point
    assert read_lifted(tmp_path / "s.pt")["source"] == "img.png"
    # a mask of one's own replaces the frontend's
    mine = torch.arange(len(fe.grid)) % 2 == 0
    save_lifted(tmp_path / "m.pt", ref.x, fe, mask=mine)
    assert torch.equal(load_lifted(tmp_path / "m.pt").mask, mine)


def test_damaged_and_foreign_files_are_refused(tmp_path, lifted):
    fe, ref = lifted
    with pytest.raises(ValueError, match=r"x \(161, 2\) and mask \(162,\) do not fit the grid "
                                         r"icosahedral:2 of 162 points"):
        save_lifted(tmp_path / "bad.pt", ref.x[:-1], fe)
    assert not (tmp_path / "bad.pt").exists()
    save_lifted(tmp_path / "s.pt", ref.x, fe)
    blob = torch.load(tmp_path / "s.pt", weights_only=True)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_lifted(tmp_path / "none.pt")
    cases = {"foreign": ({"x": ref.x}, "not a usf-graph lifted file"),
             "old": ({**blob, "version": 0}, "version 0, this usf-graph reads version 1; "
                                             "lift the image again"),
             "lacks": ({k: v for k, v in blob.items() if k != "radius"},
                       "lacks 'radius'; lift the image again"),
             "short": ({**blob, "x": blob["x"][:-2]}, r"x \(160, 2\) and mask \(162,\) do not fit "
                                                      "the grid .* the file is corrupt")}
    for name, (content, why) in cases.items():
        torch.save(content, tmp_path / f"{name}.pt")
        with pytest.raises(ValueError, match=why):
            load_lifted(tmp_path / f"{name}.pt")
    (tmp_path / "cut.pt").write_bytes((tmp_path / "s.pt").read_bytes()[:300])
    with pytest.raises(ValueError, match="not a readable lifted file .*usf-graph lift --out"):
        load_lifted(tmp_path / "cut.pt")
    torch.save({**blob, "where": tmp_path}, tmp_path / "foreign.pt")  # a pickled object
    with pytest.raises(ValueError, match=r"UnpicklingError: Unsupported global") as e:
        load_lifted(tmp_path / "foreign.pt")
    assert "weights_only" not in str(e.value)  # not torch's advice to run what the file holds
