"""The README's quick tour (every code block of the section) runs as printed, on a smaller
grid to keep the suite fast."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_quick_tour_runs(monkeypatch):
    text = (ROOT / "README.md").read_text()
    section = text.split("## Quick tour", 1)[1].split("\n## ", 1)[0]
    code = "\n".join(re.findall(r"```python\n(.*?)```", section, re.S))  # every block, in order
    assert "grids.icosahedral(6)" in code
    monkeypatch.chdir(ROOT)  # the tour loads a calibration from tests/fixtures
    ns = {}
    exec(compile(code.replace("grids.icosahedral(6)", "grids.icosahedral(4)"), "README", "exec"), ns)
    N = 10 * 4 ** 4 + 2
    assert ns["xb"].shape == (2, N, 3) and ns["y"].shape == (N, 16)
    assert ns["inv"].shape == (2, N, 16) and ns["y_coarse"].shape == (len(ns["coarse"]), 16)
    assert ns["rot"].x.shape == ns["img"].x.shape and bool(ns["valid"].all())
    assert ns["yb"].shape == (2, N, 16) and ns["g_feat"].shape == (2, 16)
    assert ns["err"] < 1e-10
