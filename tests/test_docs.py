"""The API reference: every public name documents itself, and `make docs` builds it."""

import importlib.util
import inspect
from pathlib import Path

import pytest

import usf_graph

ROOT = Path(__file__).resolve().parents[1]
SUBPACKAGES = (*usf_graph._SUBPACKAGES, "bags")


def api_docs():
    spec = importlib.util.spec_from_file_location("api_docs", ROOT / "scripts" / "api_docs.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def public_names(module):
    names = getattr(module, "__all__", None)
    if names is None:
        names = [n for n, o in vars(module).items() if not n.startswith("_")
                 and getattr(o, "__module__", None) == module.__name__]
    for n in names:
        obj = getattr(module, n)
        if inspect.isclass(obj) or inspect.isfunction(obj):
            yield n, obj


def doc_origin(cls, name):
    """The class whose definition of ``name`` gives ``cls.name`` its docstring."""
    for base in cls.__mro__:
        attr = base.__dict__.get(name)
        if attr is None:
            continue
        fn = attr.fget if isinstance(attr, property) else attr
        if getattr(fn, "__doc__", None):
            return base
    return None


def undocumented(module):
    out = []
    for n, obj in public_names(module):
        if not obj.__doc__:
            out.append(n)
        if not inspect.isclass(obj):
            continue
        for a, attr in vars(obj).items():
            fn = attr.fget if isinstance(attr, property) else attr
            if a.startswith("_") or not inspect.isfunction(fn):
                continue
            if "." not in fn.__qualname__:  # made at run time (PyG's generated collect())
                continue
            origin = doc_origin(obj, a)
            # torch's generic forward() text says nothing of shapes: forward documents itself
            own = origin is not None and (origin.__module__.startswith("usf_graph")
                                          or a != "forward")
            if not own:
                out.append(f"{n}.{a}")
    return out


@pytest.mark.parametrize("name", ["usf_graph"] + [f"usf_graph.{n}" for n in SUBPACKAGES])
def test_public_names_have_docstrings(name):
    module = importlib.import_module(name)
    assert module.__doc__, f"{name} has no module docstring"
    missing = undocumented(module)
    assert not missing, f"{name}: no docstring on {missing}"


def test_undocumented_names_are_found():
    class Plain:
        def forward(self, x):
            return x

        def run(self):
            """Runs."""

    class Layer(Plain):
        def forward(self, x):
            return x

        def run(self):
            return 1

    mod = type(inspect)("usf_graph.fake")
    mod.__all__ = ["Plain", "Layer"]
    mod.Plain, mod.Layer = Plain, Layer
    Plain.__module__ = Layer.__module__ = "usf_graph.fake"
    # Plain: no class docstring and a bare forward; Layer inherits run's docstring
    assert undocumented(mod) == ["Plain", "Plain.forward", "Layer", "Layer.forward"]


def test_api_reference_builds(tmp_path):
    pages = api_docs().build(tmp_path)
    assert "index.html" in pages and "usf_graph/nn.html" in pages
    assert {"usf_graph/cameras.html", "usf_graph/models.html", "usf_graph/datasets.html",
            "usf_graph/bags.html"} <= set(pages)
    nn = (tmp_path / "usf_graph" / "nn.html").read_text()
    # SphericalConv's equation is rendered as display math, its arguments as a list
    assert "$$\\mathbf{y}_i = \\sum_{k=1}^{K}" in nn
    assert "<li><strong>num_basis:</strong>" in nn
    # Sphinx's :class:`~a.b.C` becomes a link, without the tilde
    assert '<code><a href="#EdgePlan">usf_graph.nn.aggregate.EdgePlan</a></code>' in nn
    assert "<code>~" not in nn
