"""Mutation audit: do a module's tests fail when its code is changed?

Each mutant changes one place in the module: an arithmetic operator (+ -, * /), a
comparison (< <=, == !=, in / not in), ``and``/``or``, a ``not`` or unary minus dropped,
a number nudged, a boolean flipped, a ``raise`` removed. The named tests run against each
mutant in a scratch copy of the repository (the working tree is never touched); a mutant
the tests pass is a *survivor*: either a test is missing, or the change is equivalent
(a tolerance, a chunk size). Read each survivor and decide.

    python scripts/mutants.py usf_graph/geometry.py tests/test_geometry.py --max 40

It takes about as long as the tests, times the mutants (``--max``, drawn with ``--seed``).
"""

from __future__ import annotations

import argparse
import ast
import copy
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

ROOT = Path(__file__).resolve().parents[1]
_BINARY = {ast.Add: ast.Sub, ast.Sub: ast.Add, ast.Mult: ast.Div, ast.Div: ast.Mult,
           ast.FloorDiv: ast.Mult, ast.Pow: ast.Mult, ast.Mod: ast.FloorDiv}
_COMPARE = {ast.Lt: ast.LtE, ast.LtE: ast.Lt, ast.Gt: ast.GtE, ast.GtE: ast.Gt, ast.Eq: ast.NotEq,
            ast.NotEq: ast.Eq, ast.Is: ast.IsNot, ast.IsNot: ast.Is, ast.In: ast.NotIn,
            ast.NotIn: ast.In}
KINDS = ("operator", "compare", "unary", "number", "bool", "boolop", "raise")


class Mutant(NamedTuple):
    function: str
    line: int
    column: int
    what: str
    source: str


def _kind(node) -> list[tuple[str, str]]:
    """The (kind, description) of each mutation ``node`` offers."""
    if isinstance(node, ast.BinOp) and type(node.op) in _BINARY:
        return [("operator", f"{type(node.op).__name__} -> {_BINARY[type(node.op)].__name__}")]
    if isinstance(node, ast.Compare):
        return [("compare", f"{type(op).__name__} -> {_COMPARE[type(op)].__name__}")
                for op in node.ops if type(op) in _COMPARE]
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.Not)):
        return [("unary", f"drop {type(node.op).__name__}")]
    if isinstance(node, ast.Constant) and isinstance(node.value, bool):
        return [("bool", f"{node.value} -> {not node.value}")]
    if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)):
        return [("number", f"{node.value!r} -> {_nudged(node.value)!r}")]
    if isinstance(node, ast.BoolOp):
        return [("boolop", "and -> or" if isinstance(node.op, ast.And) else "or -> and")]
    if isinstance(node, ast.Raise):
        return [("raise", "raise -> pass")]
    return []


def _nudged(v):
    return v + 1 if isinstance(v, int) else (v * 1.5 if v else 1.0)


def _mutate(node, which: int) -> ast.AST:
    """``node`` changed by its ``which``-th mutation (a copy; ``Raise`` becomes ``Pass``)."""
    new = copy.copy(node)
    if isinstance(node, ast.BinOp):
        new.op = _BINARY[type(node.op)]()
    elif isinstance(node, ast.Compare):
        ops = [i for i, op in enumerate(node.ops) if type(op) in _COMPARE]
        new.ops = list(node.ops)
        new.ops[ops[which]] = _COMPARE[type(node.ops[ops[which]])]()
    elif isinstance(node, ast.UnaryOp):
        return node.operand
    elif isinstance(node, ast.Constant):
        new.value = not node.value if isinstance(node.value, bool) else _nudged(node.value)
    elif isinstance(node, ast.BoolOp):
        new.op = ast.Or() if isinstance(node.op, ast.And) else ast.And()
    elif isinstance(node, ast.Raise):
        return ast.copy_location(ast.Pass(), node)
    return new


class _Swap(ast.NodeTransformer):
    def __init__(self, target: int, which: int):
        self.target, self.which, self.seen = target, which, -1

    def visit(self, node):
        self.seen += 1
        if self.seen == self.target:
            return _mutate(node, self.which)
        return super().visit(node)


def mutants(source: str, functions=(), kinds=KINDS) -> list[Mutant]:
    """Every single-place mutant of ``source`` inside the named ``functions`` (all when
    empty) of the given ``kinds``, in source order."""
    tree = ast.parse(source)
    order = {id(n): i for i, n in enumerate(_walk(tree))}
    out = []
    for fn in ast.walk(tree):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        if functions and fn.name not in functions:
            continue
        body = fn.body[1:] if ast.get_docstring(fn) else fn.body  # a docstring is no code
        defaults = [d for d in (*fn.args.defaults, *fn.args.kw_defaults) if d is not None]
        for node in (n for part in (*defaults, *body) for n in ast.walk(part)):
            for which, (kind, what) in enumerate(_kind(node)):
                if kind in kinds:
                    changed = _Swap(order[id(node)], which).visit(copy.deepcopy(tree))
                    out.append(Mutant(fn.name, node.lineno, node.col_offset, what,
                                      ast.unparse(changed)))
    unique = {(m.line, m.column, m.what): m for m in out}  # nested functions repeat
    return sorted(unique.values(), key=lambda m: (m.line, m.column))


def _walk(tree):
    """The nodes in the order ``ast.NodeTransformer`` visits them (depth first)."""
    yield tree
    for child in ast.iter_child_nodes(tree):
        yield from _walk(child)


def _scratch_copy() -> Path:
    """The repository's tracked and untracked (not ignored) files, copied to a temporary
    folder."""
    files = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"],
                           cwd=ROOT, capture_output=True, text=True, check=True).stdout.split("\n")
    dest = Path(tempfile.mkdtemp(prefix="usf-mutants-"))
    for f in filter(None, files):
        if (ROOT / f).is_file():
            (dest / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / f, dest / f)
    return dest


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("module", help="the module to mutate, e.g. usf_graph/geometry.py")
    p.add_argument("tests", nargs="+", help="the test files (or node ids) to run per mutant")
    p.add_argument("--max", type=int, default=40, help="mutants to run, drawn at random (40)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--functions", default="", help="comma-separated: only these functions")
    p.add_argument("--kinds", default=",".join(KINDS), help=f"comma-separated of {', '.join(KINDS)}")
    p.add_argument("--timeout", type=float, default=600, help="seconds per mutant's tests")
    a = p.parse_args(argv)
    kinds = tuple(a.kinds.split(","))
    if unknown := set(kinds) - set(KINDS):
        p.error(f"unknown kinds {sorted(unknown)}; use {', '.join(KINDS)}")
    module = Path(a.module)
    if not (ROOT / module).is_file():
        p.error(f"{module} is not a file under {ROOT}")
    found = mutants((ROOT / module).read_text(), tuple(filter(None, a.functions.split(","))), kinds)
    chosen = sorted(random.Random(a.seed).sample(found, min(a.max, len(found))),
                    key=lambda m: (m.line, m.column))
    print(f"{module}: {len(found)} mutants, running {len(chosen)}", flush=True)
    scratch = _scratch_copy()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # a timeout still cleans up
    env = dict(os.environ, PYTHONPATH=str(scratch), PYTHONDONTWRITEBYTECODE="1")
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", "-o", "addopts=",
           "-m", "not slow", *a.tests]
    survivors = []
    try:
        for k, m in enumerate(chosen, 1):
            (scratch / module).write_text(m.source)
            t = time.perf_counter()
            try:
                rc = subprocess.run(cmd, cwd=scratch, env=env, capture_output=True,
                                    timeout=a.timeout).returncode
            except subprocess.TimeoutExpired:
                rc = "timeout"
            if rc in (4, 5):  # usage error, no tests collected: the audit itself is wrong
                raise SystemExit(f"pytest could not run {' '.join(a.tests)} (exit {rc})")
            status = "survived" if rc == 0 else "killed"
            print(f"[{k}/{len(chosen)}] {status:8s} {m.function}:{m.line}:{m.column} {m.what} "
                  f"({time.perf_counter() - t:.0f} s)", flush=True)
            if rc == 0:
                survivors.append(m)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    print(f"{len(survivors)} of {len(chosen)} survived" + "".join(
        f"\n  {m.function}:{m.line}:{m.column} {m.what}" for m in survivors))
    return 0


if __name__ == "__main__":
    sys.exit(main())
