"""Build the API reference: HTML pages from the package's docstrings, with their math.

``make docs`` runs it into ``docs/api`` (open ``docs/api/index.html``; not committed).
Every warning pdoc gives (a name in ``__all__`` that does not resolve, an annotation it
cannot read) stops the build, so the reference never silently loses a page.
"""

from __future__ import annotations

import argparse
import re
import warnings
from pathlib import Path


def modules() -> list[str]:
    """The modules to document: the package and each subpackage its ``__all__`` leaves out
    (the ones it names are reached from its page)."""
    import usf_graph

    for name in ("SphericalFrontend", "SphericalImage"):  # lazy: load them for pdoc to see
        getattr(usf_graph, name)
    rest = [n for n in (*usf_graph._SUBPACKAGES, "bags", "videos") if n not in usf_graph.__all__]
    return ["usf_graph"] + [f"usf_graph.{n}" for n in rest]


def sphinx_roles(rst):
    """pdoc's reST conversion, taking Sphinx's ``:class:`~a.b.C``` (show only ``C``) as
    ``:class:`a.b.C```, which pdoc links, instead of printing the ``~``."""
    if getattr(rst, "sphinx_roles", False):
        return rst

    def convert(contents, source_file):
        return rst(re.sub(r"(:[a-z]+:`)~", r"\1", contents), source_file)

    convert.sphinx_roles = True
    return convert


def build(out: Path) -> list[str]:
    """Write the reference into ``out``; returns the HTML files written."""
    import pdoc
    import pdoc.docstrings
    import pdoc.render

    import usf_graph

    pdoc.docstrings.rst = sphinx_roles(pdoc.docstrings.rst)
    pdoc.render.configure(docformat="google", math=True, search=True,
                          footer_text=f"usf-graph {usf_graph.__version__}")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        pdoc.pdoc(*modules(), output_directory=out)
    own = [w for w in caught if "pdoc" in Path(w.filename).parts]  # not our imports' warnings
    if own:
        raise RuntimeError("the API reference is incomplete:\n" + "\n".join(
            str(w.message) for w in own))
    return sorted(str(p.relative_to(out)) for p in out.rglob("*.html"))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("docs/api"), help="output folder")
    args = ap.parse_args(argv)
    pages = build(args.out)
    print(f"wrote {len(pages)} pages; open {args.out / 'index.html'}")


if __name__ == "__main__":
    main()
