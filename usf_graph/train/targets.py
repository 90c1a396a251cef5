"""The rooms protocols' targets (the segmentation and detection issues), read from a run's
``results.json``: which hold, and by how much.

Segmentation (mIoU on pixels, in points; judged on the best spherical model in
distribution): within 2 of the planar U-Net in distribution, or ahead; rotated within 1.0
of (a); the zero-shot fisheye and pinhole within 3 of (a); the planar U-Net loses at least
20 under rotation. Detection (AP50): the spherical detector at least 0.9x the planar one in
distribution; rotated within 1 of (a); fisheye and pinhole within 3 of (a); the planar
detector loses at least half under rotation.

"Within" is read as "no more than that below": a test that scores above (a) holds. Where it
scores above by more than the tolerance, ``both_ways`` is ``False``, for readers of the
stricter reading.
"""

from __future__ import annotations

import json
from pathlib import Path

SPHERICAL_SEG = ("spherical_unet", "spherical_deeplab")
EPS = 1e-9  # points: a gap of exactly the tolerance holds, whatever the rounding of 100 * x


def _row(target: str, value: float, holds: bool, text: str, both_ways: bool | None = None) -> dict:
    return {"target": target, "value": value, "holds": bool(holds), "text": text,
            "both_ways": holds if both_ways is None else bool(both_ways and holds)}


def _within(target: str, gap: float, tol: float) -> dict:
    return _row(target, gap, gap >= -tol - EPS, f"{gap:+.2f}", abs(gap) <= tol + EPS)


def seg_targets(res: dict) -> list[dict]:
    """The segmentation targets of a rooms run's results (``run``'s return value)."""
    models = [m for m in SPHERICAL_SEG if m in res]
    if not models:
        raise ValueError("these results hold no spherical segmentation model "
                         f"({', '.join(SPHERICAL_SEG)}); are they a 'usf-graph train seg' run's?")
    best = max(models, key=lambda m: res[m]["a"]["mIoU"])

    def pts(model, test):
        return 100 * res[model][test]["mIoU"]

    a = pts(best, "a")
    rows = [{"target": "spherical model judged (the best in distribution)", "text": best, "info": True}]
    if "planar_unet" in res:
        lead = a - pts("planar_unet", "a")
        rows.append(_row("in distribution within 2 of the planar U-Net, or ahead", lead,
                         lead >= -2 - EPS, f"{lead:+.2f}"))
    tests = res[best]
    for t, name, tol in (("b", "rotated within 1.0 of (a)", 1.0), ("c", "fisheye within 3 of (a)", 3.0),
                         ("d", "pinhole within 3 of (a)", 3.0)):
        if t in tests:
            rows.append(_within(name, pts(best, t) - a, tol))
    if "planar_unet" in res and "b" in res["planar_unet"]:
        loss = pts("planar_unet", "a") - pts("planar_unet", "b")
        rows.append(_row("the planar U-Net loses at least 20 under rotation", loss, loss >= 20 - EPS,
                         f"{loss:.2f}"))
    return rows


def hidden_centres(res: dict) -> dict:
    """An information row: whether the run records that its (c) and (d) dropped the
    detections centred where the camera does not see (``decode(..., drop_hidden=True)``).
    Runs from before that rule do not record it and scored those detections, so their (c)
    and (d) can be lower than a run today would give (:data:`UNRECORDED`)."""
    return {"target": "detections centred out of view", "info": True,
            "text": "dropped" if res.get("drop_hidden", False) else "not recorded"}


#: What to do about a detection run whose results do not record the decoding rule.
UNRECORDED = ("'not recorded': the run may predate the detectors' dropping of detections "
              "centred out of view (which can lower (c) and (d), by up to 4.8 AP50 on rooms by "
              "kind); score them again with 'usf-graph eval det RUN/spherical.pt --test c d'")


def det_targets(res: dict) -> list[dict]:
    """The detection targets of a rooms run's results."""
    if "spherical" not in res:
        raise ValueError("these results hold no spherical detector; are they a 'usf-graph "
                         "train det' run's?")

    def pts(model, test):
        return 100 * res[model][test]["AP50"]

    a, rows = pts("spherical", "a"), [hidden_centres(res)]
    if "planar" in res:
        p = pts("planar", "a")
        ratio = a / p if p > 0 else float("inf")
        rows.append(_row("spherical AP50 in distribution at least 0.9x the planar one", ratio,
                         ratio >= 0.9 - EPS, f"{ratio:.2f}x"))
    for t, name, tol in (("b", "rotated within 1 of (a)", 1.0), ("c", "fisheye within 3 of (a)", 3.0),
                         ("d", "pinhole within 3 of (a)", 3.0)):
        if t in res["spherical"]:
            rows.append(_within(f"spherical {name}", pts("spherical", t) - a, tol))
    if "planar" in res and "b" in res["planar"]:
        p = pts("planar", "a")
        loss = (p - pts("planar", "b")) / p if p > 0 else 0.0
        rows.append(_row("planar AP50 loses at least half under rotation", loss, loss >= 0.5 - EPS,
                         f"{100 * loss:.0f}%"))
    return rows


LEGEND = "bold: misses; *: holds only with 'within' read as 'no more than that below'"


def task_of(res: dict) -> str:
    """``"det"`` or ``"seg"``: the task of a run's results, told by its models' names."""
    return "det" if "spherical" in res else "seg"


def targets(res: dict) -> list[dict]:
    """The targets of a rooms run's results, its task told by its models: a list of
    ``{"target", "value", "holds", "text", "both_ways"}`` (segmentation's first row names
    the model judged, ``{"target", "text", "info": True}``)."""
    if isinstance(res.get("spherical"), dict) and "NR" in res["spherical"]:
        raise ValueError("these are the results of 'usf-graph train mnist' (NR/R accuracy, in "
                         "its results.json); the targets are the rooms protocols' (a run of "
                         "'usf-graph train seg|det')")
    det = task_of(res) == "det"
    task = det_targets if det else seg_targets
    models = ["spherical"] if det else [m for m in SPHERICAL_SEG if m in res]
    if any(not isinstance(res[m], dict) or "a" not in res[m] for m in models):
        raise ValueError("these results have no test (a): the targets are the rooms protocols' "
                         "(a run of 'usf-graph train seg|det' on rooms), not real data's")
    return task(res)


def load_results(path: str | Path) -> dict:
    """A run's results: ``path`` is its ``results.json`` or the run's folder."""
    p = Path(path)
    p = p / "results.json" if p.is_dir() else p
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no such results file; give a run folder of 'usf-graph "
                                "train seg|det' (it writes results.json) or the file itself")
    try:
        return json.loads(p.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{p} is not valid JSON ({e}); the run may have been cut short: "
                         "run it again with --resume") from None


def format_targets(runs: dict[str, list[dict]]) -> str:
    """Markdown: a row per target, a column per run (``{label: targets(...)}``); a target
    that misses is in bold, one that holds only when "within" is read one way is marked
    with an asterisk."""
    labels = list(runs)
    order = []
    for rows in runs.values():
        order += [r["target"] for r in rows if r["target"] not in order]
    lines = ["| target | " + " | ".join(labels) + " |", "|---" * (len(labels) + 1) + "|"]
    for t in order:
        cells = []
        for label in labels:
            r = next((r for r in runs[label] if r["target"] == t), None)
            cells.append("-" if r is None else r["text"] if r.get("info") or r["both_ways"] else
                         f"{r['text']}*" if r["holds"] else f"**{r['text']}**")
        lines.append(f"| {t} | " + " | ".join(cells) + " |")
    counted = {label: [r for r in rows if not r.get("info")] for label, rows in runs.items()}
    lines.append("| targets held | " + " | ".join(
        f"{sum(r['holds'] for r in counted[lb])} of {len(counted[lb])}" for lb in labels) + " |")
    return "\n".join(lines)


__all__ = ["LEGEND", "UNRECORDED", "seg_targets", "det_targets", "hidden_centres", "task_of", "targets", "load_results", "format_targets"]
