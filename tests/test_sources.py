"""The package's sources hold no control characters: math written as ``\\theta`` or
``\\nabla`` in a docstring that lost its ``r`` prefix (or was written through an escaping
editor) turns into a tab or a line break, and the docs then show garbage."""

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCES = sorted((ROOT / "usf_graph").rglob("*.py"))


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_control_characters(path):
    text = path.read_text()
    # split on "\n" only: splitlines() would also split on (and so hide) \f and \v
    bad = [n for n, ln in enumerate(text.split("\n"), 1) if any(ord(ch) < 32 for ch in ln)]
    assert not bad, f"{path.name}: control characters (tab, backspace...) on lines {bad}"
