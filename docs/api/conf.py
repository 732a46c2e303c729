"""Sphinx configuration of the API reference (``make docs``).

Each page names one public package and the ``public-modules`` directive below fills it
with an ``automodule`` of every module that the package's ``__all__`` draws on (read from
its ``__init__``, as :mod:`kpstudy._lazy` reads it), so no page lists a module, name or
signature by hand. numpydoc turns the docstrings' sections into fields; the warnings it
sends through Python's ``warnings`` (an unknown section, say) are routed to Sphinx's
logger, so that ``-W`` fails on them as on docutils' and autodoc's.
"""

import ast
import importlib.util
import pkgutil
import sys
import sysconfig
import warnings
from pathlib import Path

from sphinx.util import logging
from sphinx.util.docutils import SphinxDirective

ROOT = Path(__file__).resolve().parents[2]
#: Where installed packages live: numpydoc's warnings on their docstrings are not ours.
INSTALLED = sorted(
    {sysconfig.get_path(key) for key in ("stdlib", "platstdlib", "purelib", "platlib")}
)
sys.path.insert(0, str(ROOT))

project = "kpstudy"
author = "kpstudy"
copyright = "kpstudy"
extensions = ["sphinx.ext.autodoc", "numpydoc"]

exclude_patterns = ["_build"]
html_theme = "alabaster"
html_title = "kpstudy API reference"
html_static_path: list[str] = []

autodoc_member_order = "bysource"
autodoc_default_options = {"show-inheritance": True}
autodoc_typehints = "signature"
# numpydoc: no autosummary table of every class member (autodoc's members document them).
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False

logger = logging.getLogger("kpstudy.api")


def public_modules(package: str) -> list[str]:
    """The modules whose public names ``package``'s ``__init__`` re-exports, in its order.

    A package with ``lazy_exports(__name__, {module: names, ...})`` names its modules as
    that dict's keys; one that imports its names (``from package.module import …``) names
    them by those imports; a package with neither (``data_gen``) has every submodule
    whose name has no leading underscore; a plain module stands for itself.
    """
    spec = importlib.util.find_spec(package)
    if spec is None:
        raise ValueError(f"public-modules: no module {package!r}")
    if spec.submodule_search_locations is None:
        return [package]
    tree = ast.parse(Path(spec.origin).read_text(encoding="utf-8"))
    modules: list[str] = []
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Call)
            and getattr(node.func, "id", None) == "lazy_exports"
            and len(node.args) == 2
            and isinstance(node.args[1], ast.Dict)
        ):
            modules += [f"{package}.{ast.literal_eval(key)}" for key in node.args[1].keys]
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith(package + "."):
            modules.append(node.module)
    if not modules:
        modules = [
            f"{package}.{info.name}"
            for info in pkgutil.iter_modules(spec.submodule_search_locations)
            if not info.name.startswith("_")
        ]
    return list(dict.fromkeys(modules))


class PublicModules(SphinxDirective):
    """``.. public-modules:: package``: an ``automodule`` with members for each module of
    :func:`public_modules`."""

    required_arguments = 1

    def run(self):
        text = "".join(
            f".. automodule:: {module}\n   :members:\n\n"
            for module in public_modules(self.arguments[0])
        )
        return self.parse_text_to_nodes(text)


def _route_numpydoc_warnings() -> None:
    """Send numpydoc's Python warnings (docscrape's "Unknown section …") to Sphinx's
    logger, where ``-W`` counts them, but those on the docstrings of installed packages
    (:data:`INSTALLED`); other warnings go where they went."""
    shown = warnings.showwarning

    def showwarning(message, category, filename, lineno, file=None, line=None):
        if "numpydoc" not in Path(filename).parts:
            shown(message, category, filename, lineno, file, line)
        elif not any(f" in {path}" in str(message) for path in INSTALLED):
            logger.warning("numpydoc: %s", message, type="numpydoc")
        # else: the docstring of an installed package's object that a module imports
        # (trimesh's rotation_matrix), which autodoc reads and skips: not ours to fix.

    warnings.showwarning = showwarning
    warnings.filterwarnings("always", category=UserWarning, module=r"numpydoc\b")


def setup(app):
    app.add_directive("public-modules", PublicModules)
    _route_numpydoc_warnings()
    return {"parallel_read_safe": True}
