"""The protocols' defaults for the help screens, read from their ``run`` functions' source.

Importing ``usf_graph.train`` imports torch and PyG (6-8 s); ``usf-graph train --help``
needs only a few literals from the signatures, so it reads them from the files instead.
The functions stay the one source: ``tests/test_cli_defaults.py`` checks these values against
``inspect.signature`` of the imported functions."""

from __future__ import annotations

import ast
from functools import cache
from pathlib import Path

_TRAIN = Path(__file__).parent / "train"


@cache
def source_defaults(module: str, name: str = "run") -> dict:
    """``{argument: default}`` of function ``name`` in ``usf_graph/train/<module>.py``, for
    the defaults written as literals or as names of the module's literal constants
    (``FOV_EPOCHS = 6``); the others (calls, imported names) are left out."""
    tree = ast.parse((_TRAIN / f"{module}.py").read_text(encoding="utf-8"))
    constants = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1 \
                and isinstance(node.targets[0], ast.Name):
            try:
                constants[node.targets[0].id] = ast.literal_eval(node.value)
            except ValueError:
                pass
    fn = next((n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == name), None)
    if fn is None:
        raise LookupError(f"no function {name} in usf_graph/train/{module}.py")
    args = fn.args
    positional = args.posonlyargs + args.args
    pairs = [*zip(positional[len(positional) - len(args.defaults):], args.defaults),
             *((a, d) for a, d in zip(args.kwonlyargs, args.kw_defaults) if d is not None)]
    out = {}
    for arg, node in pairs:
        if isinstance(node, ast.Name):
            if node.id in constants:
                out[arg.arg] = constants[node.id]
            continue
        try:
            out[arg.arg] = ast.literal_eval(node)
        except ValueError:
            pass
    return out


def per_task(key: str) -> str:
    """``"det A, seg B"`` (``"det/seg A"`` when they agree): ``key``'s default in the two
    rooms protocols, for an option's help."""
    det, seg = (_show(source_defaults(task)[key]) for task in ("det", "seg"))
    return f"det/seg {det}" if det == seg else f"det {det}, seg {seg}"


def _show(value) -> str:
    """A default as help shows it: ``3e-3`` as 0.003, ``1.0`` as 1."""
    return f"{value:g}" if isinstance(value, float) else str(value)
