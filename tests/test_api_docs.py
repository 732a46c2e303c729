"""The API reference (docs/api, ``make docs``): Sphinx + numpydoc build it from the
docstrings without a warning, every cross-reference resolving (nitpicky), it holds every
public name, and a faulty docstring or a reference that does not resolve fails it."""

import importlib
import importlib.util
import inspect
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
API = ROOT / "docs" / "api"
#: The packages with a page of their own (docs/api/*.rst).
PACKAGES = (
    "kpstudy.pose",
    "kpstudy.verify",
    "kpstudy.models",
    "kpstudy.certify",
    "kpstudy.study",
    "kpstudy.io",
    "data_gen",
)


def sphinx_build(source: Path, out: Path, *, pythonpath: Path | None = None):
    """``make docs``'s build (``-W --keep-going``) of ``source`` with docs/api's conf.py."""
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    if pythonpath is not None:
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(pythonpath), env.get("PYTHONPATH")]))
    command = [sys.executable, "-m", "sphinx", "-b", "html", "-W", "--keep-going", "-q"]
    command += ["-c", str(API), str(source), str(out)]
    return subprocess.run(command, capture_output=True, text=True, env=env, timeout=600)


def inventory(out: Path) -> set[str]:
    """Every object name in the built reference's objects.inv."""
    from sphinx.util.inventory import InventoryFile

    with open(out / "objects.inv", "rb") as f:
        data = InventoryFile.load(f, "", lambda base, uri: uri)
    return {name for objects in data.values() for name in objects}


def api_conf():
    spec = importlib.util.spec_from_file_location("kpstudy_api_conf", API / "conf.py")
    conf = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(conf)
    return conf


def public_names(module: str) -> list[str]:
    """``module``'s ``__all__``, or else its public functions and classes."""
    m = importlib.import_module(module)
    if hasattr(m, "__all__"):
        return list(m.__all__)
    return [
        name
        for name, obj in vars(m).items()
        if not name.startswith("_")
        and (inspect.isfunction(obj) or inspect.isclass(obj))
        and obj.__module__ == module
    ]


def test_reference_builds_without_warnings(tmp_path):
    # Nitpicky (conf.py): every cross-reference resolves; only third-party targets are
    # ignored, never one of ours.
    conf = api_conf()
    assert conf.nitpicky
    ours = ["kpstudy", "kpstudy.verify.bab.verify", "data_gen", "data_gen.airplane.VARIANTS"]
    ours += ["verify", "Region", "OCCLUDER_NAMES"]
    for _, target in conf.nitpick_ignore_regex:
        assert not [name for name in ours if re.fullmatch(target, name)], target
    assert not {target for _, target in conf.nitpick_ignore} & set(ours)

    built = sphinx_build(API, tmp_path)
    assert built.returncode == 0 and "WARNING" not in built.stderr, built.stderr
    assert "ERROR" not in built.stderr, built.stderr
    documented = inventory(tmp_path)
    assert {f"{package}" for package in PACKAGES} <= documented
    pages = {p.stem for p in API.glob("*.rst")} - {"index"}
    assert pages == {package.rpartition(".")[2] for package in PACKAGES}

    # Every re-exported name, under its package's own modules.
    for package in PACKAGES:
        for name in getattr(importlib.import_module(package), "__all__", ()):
            assert any(
                doc.startswith(f"{package}.") and doc.endswith(f".{name}") for doc in documented
            ), f"{package}.{name} is not in the reference"
    # Every public name of every module a page documents (an undocumented function would be
    # left out by autodoc without a warning).
    for package in PACKAGES:
        modules = conf.public_modules(package)
        assert modules, package
        for module in modules:
            missing = [n for n in public_names(module) if f"{module}.{n}" not in documented]
            assert not missing, f"{module}: {missing} are not in the reference (no docstring?)"


FAULTY = '''
def f(x):
    """Return ``x``, for |x| below 1.

    Parameters
    ----------
    x : Tensor, shape (n, *S)
        The input.

    Frobnicate
    ----------
    Not a numpydoc section.
    """
    return x
'''


@pytest.mark.parametrize("faulty", [False, True], ids=["clean", "faulty"])
def test_a_docstring_fault_fails_the_build(tmp_path, faulty):
    """The build's ``-W`` catches docutils' warnings and numpydoc's (routed by conf.py)."""
    package = tmp_path / "modules" / "apidocs_probe"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text('"""A probe package."""\n')
    clean = '\ndef f(x):\n    """Return ``x``.\n\n    Returns\n    -------\n    object\n    """\n'
    (package / "probe.py").write_text(textwrap.dedent(FAULTY if faulty else clean))
    source = tmp_path / "source"
    source.mkdir()
    (source / "index.rst").write_text("Probe\n=====\n\n.. public-modules:: apidocs_probe\n")

    built = sphinx_build(source, tmp_path / "html", pythonpath=tmp_path / "modules")
    if not faulty:
        assert built.returncode == 0 and "WARNING" not in built.stderr, built.stderr
        assert "apidocs_probe.probe.f" in inventory(tmp_path / "html")
        return
    assert built.returncode != 0
    for warning in (
        "numpydoc: Unknown section Frobnicate",
        'Undefined substitution referenced: "x"',
        "Inline emphasis start-string without end-string",
    ):
        assert warning in built.stderr, built.stderr


UNRESOLVED = '''
from kpstudy.verify.graph import Graph


def f(graph: Graph, x: numpy.ndarray):
    """Return ``x``, as :func:`g` does; :func:`kpstudy.verify.no_such_function` and
    :class:`kpstudy.verify.graph.Graph` (an object the reference does not document).
    """
    return x


def g(x):
    """Return ``x``."""
    return x
'''


@pytest.mark.parametrize("faulty", [False, True], ids=["clean", "faulty"])
def test_a_reference_that_does_not_resolve_fails_the_build(tmp_path, faulty):
    """The build is nitpicky: a docstring's role that names a kpstudy object the reference
    does not hold fails it, whether no such object exists or it has no entry (a module
    without a page: written as ``code`` instead). Third-party names and the annotations of
    kpstudy objects without an entry (autodoc's, not the docstring's) do not."""
    package = tmp_path / "modules" / "apidocs_probe"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text('"""A probe package."""\n')
    source = "import numpy\n" + UNRESOLVED
    if not faulty:
        source = source.replace(":func:`kpstudy.verify.no_such_function`", "``g``")
        source = source.replace(":class:`kpstudy.verify.graph.Graph`", "``Graph``")
    (package / "probe.py").write_text(source)
    pages = tmp_path / "source"
    pages.mkdir()
    (pages / "index.rst").write_text("Probe\n=====\n\n.. public-modules:: apidocs_probe\n")

    built = sphinx_build(pages, tmp_path / "html", pythonpath=tmp_path / "modules")
    if not faulty:
        assert built.returncode == 0 and "WARNING" not in built.stderr, built.stderr
        assert {"apidocs_probe.probe.f", "apidocs_probe.probe.g"} <= inventory(tmp_path / "html")
        return
    assert built.returncode != 0
    for warning in (
        "py:func reference target not found: kpstudy.verify.no_such_function",
        "py:class reference target not found: kpstudy.verify.graph.Graph",
    ):
        assert warning in built.stderr, built.stderr
    assert built.stderr.count("reference target not found") == 2, built.stderr
