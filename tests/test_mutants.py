"""scripts/mutants.py: the mutation audit makes the mutants it says, and finds survivors."""

import ast

from tests.helpers import load_script

SOURCE = '''
def f(a, b):
    """A docstring with 3 numbers: 1.5 is not code."""
    if not a < b:
        raise ValueError("a must be below b")
    return -a * 2 + b


def g(flag=True):
    return flag and 0.5
'''


def _run(source, name, *args):
    scope = {}
    exec(compile(source, "<mutant>", "exec"), scope)
    try:
        return scope[name](*args)
    except ValueError:
        return "raised"


def test_each_mutant_changes_one_place_and_behaves_differently():
    mutants = load_script("scripts/mutants.py").mutants
    found = mutants(SOURCE)
    assert [(m.function, m.line, m.what) for m in found] == [
        ("f", 4, "drop Not"), ("f", 4, "Lt -> LtE"), ("f", 5, "raise -> pass"),
        ("f", 6, "Add -> Sub"), ("f", 6, "Mult -> Div"), ("f", 6, "drop USub"),
        ("f", 6, "2 -> 3"), ("g", 9, "True -> False"), ("g", 10, "and -> or"),
        ("g", 10, "0.5 -> 0.75")]
    assert ast.get_docstring(ast.parse(found[0].source).body[0]) == ast.get_docstring(ast.parse(SOURCE).body[0])
    for m in found:  # each differs from the original on these inputs
        name, cases = ("f", [(1, 3), (3, 1), (2, 2)]) if m.function == "f" else ("g", [(), (1,)])
        assert [_run(m.source, name, *c) for c in cases] != [_run(SOURCE, name, *c) for c in cases], m.what
    only = mutants(SOURCE, functions=("g",), kinds=("bool",))
    assert [m.what for m in only] == ["True -> False"]


def test_the_audit_runs_tests_against_each_mutant_in_a_scratch_copy(capsys):
    """On the chord's conversion: two of its three operators changed (drawn with seed 0:
    the torch form's division and the numpy form's), and the torch form's test alone
    catches the first and lets the second survive; the working tree is left as it was."""
    script = load_script("scripts/mutants.py")
    path = script.ROOT / "usf_graph" / "geometry.py"
    before = path.read_text()
    torch_test = "tests/test_geometry.py::test_chord_geodesic_torch_matches_numpy_with_gradients"
    args = ["usf_graph/geometry.py", torch_test, "--functions", "geodesic_to_chord", "--kinds",
            "operator", "--max", "2"]
    assert script.main(args) == 0
    out = capsys.readouterr().out
    assert "3 mutants, running 2" in out and out.count("killed") == 1
    line = next(i for i, t in enumerate(before.splitlines(), 1) if "np.sin(np.asarray(d) / 2)" in t)
    column = before.splitlines()[line - 1].index("np.asarray(d) / 2")
    assert f"1 of 2 survived\n  geodesic_to_chord:{line}:{column}" in out
    assert path.read_text() == before
