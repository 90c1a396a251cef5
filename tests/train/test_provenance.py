"""Checkpoints and results say which code and command made them."""

import json
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import torch_geometric

import usf_graph
from tests.helpers import tiny_seg_checkpoint
from usf_graph.train import load_checkpoint
from usf_graph.train.checkpoints import load_protocol_model
from usf_graph.train.engine import write_results
from usf_graph.train.provenance import describe, differs, git_state, provenance

ROOT = Path(__file__).resolve().parents[2]


def test_provenance_names_the_code_libraries_and_command(monkeypatch):
    monkeypatch.setattr(sys, "argv", ["/somewhere/bin/usf-graph", "train", "seg", "--out",
                                      "my runs/a"])
    git_state.cache_clear()  # read HEAD now (the cache is per process)
    p = provenance()
    assert p["usf_graph"] == usf_graph.__version__ and p["torch"] == torch.__version__
    assert p["torch_geometric"] == torch_geometric.__version__
    assert p["command"] == "usf-graph train seg --out 'my runs/a'"
    assert shlex.split(p["command"])[-1] == "my runs/a"  # a shell gives back the arguments
    assert p["threads"] == torch.get_num_threads() and p["time"].endswith("+00:00")
    if not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True,
                          text=True, check=True).stdout.strip()
    assert p["git"]["commit"] == head
    assert describe(p).startswith(f"usf-graph {usf_graph.__version__} (commit {head[:10]}")
    assert describe(p).endswith(": usf-graph train seg --out 'my runs/a'")


def test_checkpoints_keep_it_and_old_ones_load(tmp_path):
    tiny_seg_checkpoint(tmp_path / "seg.pt")
    blob = load_checkpoint(tmp_path / "seg.pt")
    assert blob["provenance"]["usf_graph"] == usf_graph.__version__
    assert load_protocol_model(tmp_path / "seg.pt").provenance == blob["provenance"]
    del blob["provenance"]  # as saved before session 51
    torch.save(blob, tmp_path / "old.pt")
    old = load_protocol_model(tmp_path / "old.pt")
    assert old.provenance is None
    assert describe(None) == "no provenance recorded (made before session 51)"


def test_differs_says_when_other_code_made_a_result(monkeypatch):
    now = {"commit": "a" * 40, "dirty": False}
    monkeypatch.setattr("usf_graph.train.provenance.git_state", lambda: now)
    same = {"usf_graph": usf_graph.__version__, "git": dict(now)}
    assert differs(same) is None and differs(None) is None
    assert differs({**same, "git": {"commit": "b" * 40, "dirty": True}}) == \
        "made at commit bbbbbbbbbb, scored at aaaaaaaaaa"
    assert differs({"usf_graph": "0.0.1", "git": None}) == \
        f"made by usf-graph 0.0.1, scored by {usf_graph.__version__}"


def test_results_json_carries_it(tmp_path):
    res = write_results(tmp_path / "run", {"acc": 0.5}, t0=0.0)
    on_disk = json.loads((tmp_path / "run" / "results.json").read_text())
    assert on_disk["acc"] == 0.5 and on_disk["provenance"] == res["provenance"]
    assert on_disk["provenance"]["git"] == git_state()
    assert [p.name for p in (tmp_path / "run").iterdir()] == ["results.json"]  # no temp file


def test_predict_prints_what_made_the_checkpoint(tmp_path, capsys):
    """``eval``, ``predict`` and ``export`` share it (``cli_det.ready_model``)."""
    from usf_graph.cli import main

    tiny_seg_checkpoint(tmp_path / "seg.pt")
    blob = load_checkpoint(tmp_path / "seg.pt")
    blob["provenance"]["git"] = {"commit": "c" * 40, "dirty": False}
    torch.save(blob, tmp_path / "other.pt")
    np.save(tmp_path / "pano.npy", np.random.default_rng(0).random((48, 96, 3), np.float32))
    for name in ("seg.pt", "other.pt"):
        assert main(["predict", "seg", str(tmp_path / name), str(tmp_path / "pano.npy"),
                     "--camera", "equirectangular", "--out", str(tmp_path / "p")]) == 0
        out = capsys.readouterr().out
        assert f"{tmp_path / name}: usf-graph {usf_graph.__version__}" in out
        other_code = f"note: {tmp_path / name} was made at commit cccccccccc"
        assert (other_code in out) == (name == "other.pt" and git_state() is not None)


@pytest.mark.parametrize("argv", [[], [""]])  # an embedding host; `python -c`
def test_provenance_without_a_command_line_says_so(monkeypatch, argv):
    monkeypatch.setattr(sys, "argv", argv)
    p = provenance()
    assert p["command"] == ""
    assert describe({**p, "git": None}) == f"usf-graph {usf_graph.__version__}, {p['time']}: ?"
    made = {"usf_graph": "0.1", "git": {"commit": "0123456789abcdef", "dirty": True}, "time": "T"}
    assert describe(made) == "usf-graph 0.1 (commit 0123456789, with uncommitted changes), T: ?"
