"""Sphinx configuration of the API reference (``make docs``).

Each page names one public package and the ``public-modules`` directive below fills it
with an ``automodule`` of every module that the package's ``__all__`` draws on (read from
its ``__init__``, as :mod:`kpstudy._lazy` reads it), so no page lists a module, name or
signature by hand. numpydoc turns the docstrings' sections into fields; the warnings it
sends through Python's ``warnings`` (an unknown section, say) are routed to Sphinx's
logger, so that ``-W`` fails on them as on docutils' and autodoc's.

The build is nitpicky: every cross-reference must resolve, so a docstring's role that
names a kpstudy or data_gen object must name it where the reference documents it (a
re-export by its module's path, ``:func:`~kpstudy.verify.bab.verify```), and one that has
no entry (a private helper, a module without a page) is written as ````code````. Only
third-party targets are ignored (:data:`THIRD_PARTY`; the build is offline, so there is
no intersphinx), and what autodoc itself writes that a docstring cannot change, the
annotations and base classes of kpstudy objects the reference does not document, is
shown as plain text (:func:`_unlinked_bases`, :func:`_unlinked_annotation`).
"""

import ast
import dataclasses
import functools
import importlib.util
import inspect
import pkgutil
import re
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
# numpydoc_xref_param_type stays off: the sections' types ("ndarray, shape (n, 3)",
# "int, optional") are text, so no reference comes from them.

# Every cross-reference must resolve (-W fails the build on one that does not).
nitpicky = True
#: Third-party packages (and numpy's ``np``, in annotations autodoc cannot evaluate)
#: whose names the signatures and docstrings refer to: offline, without intersphinx,
#: those references cannot resolve and are not checked. Never kpstudy or data_gen.
THIRD_PARTY = (
    "numpy",
    "np",
    "torch",
    "pandas",
    "pathlib",
    "collections.abc",
    "typing",
    "matplotlib",
    "trimesh",
    "moderngl",
    "scipy",
    "cvxpy",
    "PIL",
    "dask",
    "onnx",
)
nitpick_ignore_regex = [
    (r"py:.*", rf"(?:{'|'.join(re.escape(package) for package in THIRD_PARTY)})(?:\..+)?")
]
# torch's docstring of nn.Module.forward, which autodoc shows for a forward method
# without one of its own, refers to :class:`Module` (torch.nn.Module).
nitpick_ignore = [("py:class", "Module")]

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


#: The roots of the packages the reference documents.
OURS = ("kpstudy", "data_gen")


@functools.cache
def documented_modules(srcdir) -> tuple[frozenset[str], frozenset[str]]:
    """The modules that the pages under ``srcdir`` document: all of them (their
    ``automodule`` and ``public-modules``), and those whose members they document (the
    :func:`public_modules` of their ``public-modules``)."""
    modules: set[str] = set()
    members: set[str] = set()
    for page in Path(srcdir).rglob("*.rst"):
        text = page.read_text(encoding="utf-8")
        for kind, name in re.findall(r"^\.\. (automodule|public-modules):: *(\S+)", text, re.M):
            if kind == "automodule":
                modules.add(name)
            else:
                members.update(public_modules(name))
    return frozenset(modules | members), frozenset(members)


def _lookup(target: str):
    """``(module, object)`` of a dotted kpstudy or data_gen name (the longest importable
    module, then attributes), or None where there is no such object."""
    if target.partition(".")[0] not in OURS:
        return None
    parts = target.split(".")
    for cut in range(len(parts), 0, -1):
        module = ".".join(parts[:cut])
        try:
            obj = importlib.import_module(module)
        except ImportError:
            continue
        try:
            for part in parts[cut:]:
                obj = getattr(obj, part)
        except AttributeError:
            return None
        return module, obj
    return None


def is_documented(target: str, srcdir) -> bool:
    """Whether the pages under ``srcdir`` document the kpstudy or data_gen object named
    ``target``: a module they document, or a public name (in its module's ``__all__``
    where it has one) defined in a module whose members they document, every attribute
    below it public. A re-export is documented under its defining module only. It does
    not ask for a docstring, so it errs towards a link: one the build lacks still warns."""
    found = _lookup(target)
    if found is None:
        return False
    module, _ = found
    modules, members = documented_modules(srcdir)
    if target == module:
        return module in modules
    names = target[len(module) + 1 :].split(".")
    namespace = sys.modules[module]
    top = getattr(namespace, names[0])
    defined_here = not (inspect.isclass(top) or inspect.isroutine(top)) or (
        top.__module__ == module
    )
    exported = getattr(namespace, "__all__", None)
    return (
        module in members
        and defined_here
        and not any(name.startswith("_") for name in names)
        and (exported is None or names[0] in exported)
    )


def _unlinked_bases(app, name, obj, options, bases) -> None:
    """A base class of ours that the reference does not document (``_CornerNodes``,
    ``kpstudy.models.base.HeatmapBackbone``) is named as code, not as a reference."""
    for i, base in enumerate(bases):
        if getattr(base, "__module__", "").partition(".")[0] in OURS:
            target = f"{base.__module__}.{base.__qualname__}"
            if not is_documented(target, app.srcdir):
                bases[i] = f"``{target}``"


def _unlinked_annotation(app, env, node, contnode):
    """A signature's annotation (autodoc's, not a docstring's role: those have
    ``refexplicit``) that names an existing kpstudy or data_gen object the reference does
    not document (``kpstudy.verify.graph.Graph``) is shown as text; any other reference
    that does not resolve is left to warn."""
    target = node.get("reftarget", "")
    if (
        node.get("refdomain") == "py"
        and "refexplicit" not in node
        and _lookup(target) is not None
        and not is_documented(target, app.srcdir)
    ):
        return contnode
    return None


def _dataclass_factories(app, what, name, obj, options, signature, return_annotation):
    """A dataclass field's ``default_factory`` shows as ``<factory>`` in its signature,
    which Sphinx cannot parse (it then splits the parameters at every comma, ``dict[str``
    included): write the factory's call, ``list()``, or ``...`` for a lambda."""
    if what != "class" or not signature or "<factory>" not in signature:
        return None
    if not dataclasses.is_dataclass(obj):
        return None
    for field in dataclasses.fields(obj):
        if field.init and field.default_factory is not dataclasses.MISSING:
            call = getattr(field.default_factory, "__name__", "")
            signature = signature.replace(
                "<factory>", f"{call}()" if call.isidentifier() else "...", 1
            )
    return signature, return_annotation


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
    app.connect("autodoc-process-bases", _unlinked_bases)
    app.connect("autodoc-process-signature", _dataclass_factories)
    app.connect("missing-reference", _unlinked_annotation)
    _route_numpydoc_warnings()
    return {"parallel_read_safe": True}
