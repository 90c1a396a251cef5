"""The protocols' targets read from results: the gaps and verdicts on hand-made results, the
table, and `usf-graph targets` on run folders."""

import json

import pytest

from usf_graph.cli import main
from usf_graph.train.targets import det_targets, format_targets, load_results, seg_targets, targets


def _seg(unet, deeplab, planar):
    """Results as `train seg` writes them, from mIoU in points per test (a)-(e)."""
    res = {"samples": {"train": 4, "test": 2}}
    for name, row in (("spherical_unet", unet), ("spherical_deeplab", deeplab), ("planar_unet", planar)):
        if row is not None:
            res[name] = {t: {"mIoU": v / 100} for t, v in zip("abcde", row)}
    return res


def _det(spherical, planar):
    res = {"spherical": {t: {"AP50": v / 100} for t, v in zip("abcd", spherical)}}
    if planar is not None:
        res["planar"] = {t: {"AP50": v / 100} for t, v in zip("abcd", planar)}
    return res


def _by_name(rows):
    return {r["target"]: r for r in rows}


def test_segmentation_targets_judge_the_best_spherical_model():
    rows = _by_name(seg_targets(_seg([20, 20, 20, 20, 20], [30, 31.5, 26.9, 27.0, 30], [31.5, 10, 25, 20, 20])))
    assert rows["spherical model judged (the best in distribution)"]["text"] == "spherical_deeplab"
    cases = {"in distribution within 2 of the planar U-Net, or ahead": (-1.5, True, "-1.50"),
             "rotated within 1.0 of (a)": (1.5, True, "+1.50"),
             "fisheye within 3 of (a)": (-3.1, False, "-3.10"),
             "pinhole within 3 of (a)": (-3.0, True, "-3.00"),
             "the planar U-Net loses at least 20 under rotation": (21.5, True, "21.50")}
    for target, (value, holds, text) in cases.items():
        r = rows[target]
        assert r["value"] == pytest.approx(value) and r["holds"] is holds and r["text"] == text
    # 1.5 above (a) holds, but not with "within" read both ways
    assert rows["rotated within 1.0 of (a)"]["both_ways"] is False
    assert rows["pinhole within 3 of (a)"]["both_ways"] is True


def test_detection_targets_ratio_and_relative_loss():
    rows = _by_name(det_targets(_det([9.0, 7.9, 6.0, 5.9], [10.0, 5.0, 9, 9])))
    assert rows["spherical AP50 in distribution at least 0.9x the planar one"]["text"] == "0.90x"
    assert rows["spherical AP50 in distribution at least 0.9x the planar one"]["holds"]
    assert not rows["spherical rotated within 1 of (a)"]["holds"]
    assert rows["spherical rotated within 1 of (a)"]["value"] == pytest.approx(-1.1)
    assert rows["spherical rotated within 1 of (a)"]["text"] == "-1.10"
    assert rows["spherical fisheye within 3 of (a)"]["holds"] is True  # -3.00 exactly
    assert rows["spherical pinhole within 3 of (a)"]["holds"] is False
    assert rows["planar AP50 loses at least half under rotation"]["text"] == "50%"
    assert rows["planar AP50 loses at least half under rotation"]["holds"]
    # without the planar baseline (--no-planar) only the spherical targets are asked
    assert [r["target"] for r in det_targets(_det([9.0, 8.2, 6.0, 5.9], None))] == [
        "detections centred out of view", "spherical rotated within 1 of (a)", "spherical fisheye within 3 of (a)",
        "spherical pinhole within 3 of (a)"]


def test_detection_targets_say_how_hidden_centres_were_scored():
    """Runs before the detectors dropped detections centred out of view do not record the
    rule; their table says so and how to score (c) and (d) again, and counts no target."""
    old, new = _det([9.0, 9.2, 8.0, 5.0], [2.0, 0.2, 3, 4]), {"drop_hidden": True}
    new.update(old)
    row = _by_name(det_targets(old))["detections centred out of view"]
    assert row["info"] and row["text"] == "not recorded"
    assert _by_name(det_targets(new))["detections centred out of view"]["text"] == "dropped"
    assert format_targets({"old": det_targets(old)}).splitlines()[-1] == "| targets held | 4 of 5 |"


def test_targets_refuse_results_that_are_not_a_rooms_protocols():
    with pytest.raises(ValueError, match="no spherical segmentation model"):
        targets({"planar_unet": {"a": {"mIoU": 0.2}}})
    with pytest.raises(ValueError, match="no test"):
        targets({"spherical_unet": {"mean": {"mIoU": 0.2}}})  # Stanford 2D-3D-S's form
    with pytest.raises(ValueError, match="results of 'usf-graph train mnist'"):
        targets({"samples": {"train": 4000, "test": 1000}, "spherical": {"NR": 0.9, "R": 0.9},
                 "planar": {"NR": 0.98, "R": 0.3}})


def test_format_targets_marks_misses_and_one_way_holds():
    table = format_targets({"one": seg_targets(_seg(None, [30, 31.5, 26, 27.0, 30], [31.5, 10, 25, 20, 20])),
                            "two": seg_targets(_seg(None, [30, 30, 30, 30, 30], [29, 5, 25, 20, 20]))})
    lines = table.splitlines()
    assert lines[0] == "| target | one | two |"
    assert "| rotated within 1.0 of (a) | +1.50* | +0.00 |" in lines
    assert "| fisheye within 3 of (a) | **-4.00** | +0.00 |" in lines
    assert lines[-1] == "| targets held | 4 of 5 | 5 of 5 |"


def test_targets_command_reads_run_folders(tmp_path, capsys):
    for name, res in (("s0", _det([9.0, 9.2, 8.0, 5.0], [2.0, 0.2, 3, 4])),
                      ("s1", _det([10.0, 9.5, 9.0, 9.0], [2.5, 0.5, 3, 4]))):
        (tmp_path / name).mkdir()
        (tmp_path / name / "results.json").write_text(json.dumps(res))
    assert main(["targets", str(tmp_path / "s0"), str(tmp_path / "s1" / "results.json")]) == 0
    out = capsys.readouterr().out
    assert "| spherical pinhole within 3 of (a) | **-4.00** | -1.00 |" in out
    assert "| targets held | 4 of 5 | 5 of 5 |" in out
    assert "| detections centred out of view | not recorded | not recorded |" in out
    assert "score them again with 'usf-graph eval det RUN/spherical.pt --test c d'" in out
    (tmp_path / "new").mkdir()
    (tmp_path / "new" / "results.json").write_text(json.dumps({"drop_hidden": True, **_det([9.0] * 4, None)}))
    assert main(["targets", str(tmp_path / "new")]) == 0
    out = capsys.readouterr().out
    assert "| detections centred out of view | dropped |" in out and "score them again" not in out
    (tmp_path / "seg").mkdir()
    (tmp_path / "seg" / "results.json").write_text(json.dumps(_seg(None, [30] * 5, [29] * 5)))
    assert main(["targets", str(tmp_path / "s0"), str(tmp_path / "seg")]) == 2
    assert "mix segmentation and detection" in capsys.readouterr().err
    (tmp_path / "cut").mkdir()
    (tmp_path / "cut" / "results.json").write_text('{"spherical": ')
    with pytest.raises(ValueError, match="not valid JSON"):
        load_results(tmp_path / "cut")
    assert main(["targets", str(tmp_path / "none")]) == 2
    assert "no such results file" in capsys.readouterr().err


def test_a_finished_protocol_prints_its_targets_and_a_planar_only_run_none(capsys):
    from usf_graph.cli_det import print_targets

    print_targets(_det([9.0, 9.2, 8.0, 5.0], [2.0, 0.2, 3, 4]), "runs/det")
    out = capsys.readouterr().out
    assert "| target | runs/det |" in out and "| targets held | 4 of 5 |" in out
    print_targets({"planar_unet": {"a": {"mIoU": 0.2}}}, None)  # seg --models planar_unet
    assert capsys.readouterr().out.startswith("No targets: these results hold no spherical")


def test_every_target_holds_at_its_bound_and_misses_a_hundredth_past_it():
    """Each verdict at its boundary, both sides: (a) = 30 for the judged model; and the
    planar detector at 0 AP50 (no ratio to divide by, no loss) and at 0.5."""
    def seg(**kw):
        d = {"a": 30.0, "b": 29.0, "c": 27.0, "d": 27.0, "pa": 32.0, "pb": 12.0, **kw}
        return _by_name(seg_targets(_seg(None, [d["a"], d["b"], d["c"], d["d"], 30.0],
                                         [d["pa"], d["pb"], 25.0, 20.0, 20.0])))

    for name, at, past in (("in distribution within 2 of the planar U-Net, or ahead", {"pa": 32.0}, {"pa": 32.01}),
                           ("rotated within 1.0 of (a)", {"b": 29.0}, {"b": 28.99}),
                           ("fisheye within 3 of (a)", {"c": 27.0}, {"c": 26.99}),
                           ("pinhole within 3 of (a)", {"d": 27.0}, {"d": 26.99}),
                           ("the planar U-Net loses at least 20 under rotation", {"pb": 12.0}, {"pb": 12.01})):
        assert seg(**at)[name]["holds"] is True and seg(**past)[name]["holds"] is False, name
    assert seg(b=31.0)["rotated within 1.0 of (a)"]["both_ways"] is True
    assert seg(b=31.01)["rotated within 1.0 of (a)"]["both_ways"] is False

    def det(sph, planar):
        return _by_name(det_targets(_det(sph, planar)))

    ratio = "spherical AP50 in distribution at least 0.9x the planar one"
    loss = "planar AP50 loses at least half under rotation"
    assert det([9.0] * 4, [10.01, 5, 9, 9])[ratio]["holds"] is False
    for name, k, past in (("spherical rotated within 1 of (a)", 1, 7.99),
                          ("spherical fisheye within 3 of (a)", 2, 5.99),
                          ("spherical pinhole within 3 of (a)", 3, 5.99)):
        row = [9.0, 8.0, 6.0, 6.0]  # each at its bound
        assert det(row, None)[name]["holds"] is True
        row[k] = past
        assert det(row, None)[name]["holds"] is False, name
    assert det([9.0] * 4, [10.0, 5.01, 9, 9])[loss]["holds"] is False
    assert det([9.0] * 4, [10.0, 2.5, 9, 9])[loss]["text"] == "75%"
    none = det([9.0] * 4, [0.0, 0.0, 0, 0])
    assert none[ratio]["value"] == float("inf") and none[ratio]["holds"]
    assert none[loss]["value"] == 0.0 and not none[loss]["holds"]
    assert det([9.0] * 4, [0.5, 0.5, 0, 0])[ratio]["text"] == "18.00x"
    table = format_targets({"one": det_targets(_det([9.0] * 4, None)), "two": det_targets(_det([9.0] * 4, None))})
    assert table.splitlines()[1] == "|---|---|---|"
