"""The package tree follows the pipeline: each part of kpstudy imports only the parts before
it (docs/design.md §2, "What each part may import"). Every import of every module of
kpstudy and data_gen counts, function-level ones included, read with ``ast`` (nothing is
imported).

The tests mirror the tree (docs/design.md §2, "Tests"): module ``kpstudy/<package>/<m>.py``
is tested in ``tests/kpstudy/<package>/test_<m>.py`` (a leading underscore dropped),
``data_gen/<m>.py`` in ``tests/data_gen/test_<m>.py``; a module without a test file of its
own is listed in :data:`EXEMPT` with the reason, and a top-level ``tests/test_*.py`` is a
check across the tree (:data:`ACROSS`)."""

import ast
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TESTS = ROOT / "tests"
DESIGN = ROOT / "docs" / "design.md"

INFRASTRUCTURE = ("kpstudy", "kpstudy._checks", "kpstudy._lazy", "kpstudy._memo", "kpstudy.io")
SUBPACKAGES = ("kpstudy.pose", "kpstudy.verify", "kpstudy.models", "kpstudy.certify")
SUBPACKAGES += ("kpstudy.study",)
ENTRY = ("kpstudy.cli", "kpstudy.__main__")

#: Part → the parts (or single modules) it may import besides itself, in pipeline order.
#: docs/design.md §2 states the same table; test_the_design_states_the_rule keeps them equal.
ALLOWED = {
    "infrastructure": (),
    "kpstudy.pose": ("infrastructure",),
    "kpstudy.verify": ("infrastructure",),
    "kpstudy.models": ("infrastructure", "kpstudy.pose", "kpstudy.verify", "data_gen"),
    "kpstudy.certify": ("infrastructure", "kpstudy.pose", "kpstudy.verify", "kpstudy.models"),
    "kpstudy.study": (
        "infrastructure",
        "kpstudy.pose",
        "kpstudy.verify",
        "kpstudy.models",
        "kpstudy.certify",
        "data_gen",
    ),
    "kpstudy.cli": ("*",),
    "data_gen": ("infrastructure", "kpstudy.models.preprocess", "kpstudy.cli"),
}


def part_of(module: str) -> str | None:
    """The part of the tree ``module`` belongs to (None: not a kpstudy or data_gen module)."""
    if module in INFRASTRUCTURE:
        return "infrastructure"
    if module in ENTRY:
        return "kpstudy.cli"
    for part in (*SUBPACKAGES, "data_gen"):
        if module == part or module.startswith(part + "."):
            return part
    if module.startswith("kpstudy."):
        return "unplaced"
    return None


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def is_module(name: str, root: Path = ROOT) -> bool:
    path = root.joinpath(*name.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def imported(path: Path, root: Path = ROOT) -> list[tuple[int, str]]:
    """``(line, module)`` of every import in ``path``: ``from A import b`` names ``A.b``
    where that is a module, else ``A``; relative imports are resolved."""
    name = module_name(path, root)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([node.module] if node.module else []))
            for alias in node.names:
                full = f"{base}.{alias.name}"
                found.append((node.lineno, full if is_module(full, root) else base))
    return found


def modules():
    return sorted(p for package in ("kpstudy", "data_gen") for p in (ROOT / package).rglob("*.py"))


def violations(path: Path, root: Path = ROOT) -> list[str]:
    source = part_of(module_name(path, root))
    allowed = ALLOWED.get(source, ())
    found = []
    for line, target in imported(path, root):
        part = part_of(target)
        if part is None or part == source or "*" in allowed:
            continue
        if part in allowed or any(target == a or target.startswith(a + ".") for a in allowed):
            continue
        found.append(f"{path.relative_to(root)}:{line}: {source} imports {target} ({part})")
    return found


def test_every_module_has_a_part():
    unplaced = [module_name(p) for p in modules() if part_of(module_name(p)) == "unplaced"]
    assert not unplaced, f"place these in a subpackage (docs/design.md §2): {unplaced}"


@pytest.mark.parametrize("path", modules(), ids=lambda p: str(p.relative_to(ROOT)))
def test_imports_follow_the_pipeline(path):
    assert not violations(path), "\n".join(violations(path))


def test_the_checker_sees_function_level_and_relative_imports(tmp_path):
    for package in ("kpstudy", "kpstudy/pose", "kpstudy/study", "kpstudy/certify"):
        (tmp_path / package).mkdir(exist_ok=True)
        (tmp_path / package / "__init__.py").write_text("")
    (tmp_path / "kpstudy" / "study" / "tables.py").write_text("")
    bad = tmp_path / "kpstudy" / "pose" / "geometry.py"
    bad.write_text(
        "from kpstudy import _checks\n\n\n"
        "def late():\n    from kpstudy.study import tables\n    from ..certify import certify\n"
    )
    found = violations(bad, tmp_path)
    assert len(found) == 2, found
    assert "kpstudy.pose imports kpstudy.study.tables (kpstudy.study)" in found[0]
    assert "kpstudy.pose imports kpstudy.certify (kpstudy.certify)" in found[1]


def test_the_design_states_the_rule():
    text = DESIGN.read_text(encoding="utf-8")

    def cell(names):
        return ", ".join(n if n in ("infrastructure", "*") else f"`{n}`" for n in names) or "—"

    for part, names in ALLOWED.items():
        name = part if part == "infrastructure" else f"`{part}`"
        row = f"| {name} | {cell(names).replace('*', 'anything')} |"
        assert row in text, f"docs/design.md §2 should have the row {row}"


# -- the tests' mirror of the tree ---------------------------------------------------------

#: Modules without a test file of their own → the reason.
EXEMPT = {
    "kpstudy/__main__.py": "calls kpstudy.cli.main; tests/kpstudy/test_cli.py runs it",
    "data_gen/__main__.py": "calls data_gen.cli.main; tests/data_gen/test_cli.py runs it",
}

#: The top-level test files: checks across the tree or against outside programs → what.
ACROSS = {
    "test_layout.py": "the package tree and the tests' mirror of it",
    "test_readme.py": "the README's worked example, run as written",
    "test_examples.py": "the runnable examples of docs/examples",
    "test_api_docs.py": "the API reference's build",
    "test_marabou.py": "Marabou, an outside oracle for kpstudy.verify",
    "test_neuralsat.py": "NeuralSAT, a second outside oracle for kpstudy.verify",
    "test_reference_results.py": "the committed reference results under docs/results",
}

#: What else a mirror folder may hold besides test files.
MIRROR_EXTRAS = ("__init__.py", "conftest.py")


def mirror_of(module: Path) -> Path:
    """The test file of a module file: tests/<its folder>/test_<name>.py, the name without
    a leading underscore."""
    relative = module.relative_to(ROOT)
    return TESTS / relative.parent / f"test_{relative.stem.lstrip('_')}.py"


def module_files():
    return [p for p in modules() if p.name != "__init__.py"]


def mirror_files():
    return sorted(p for package in ("kpstudy", "data_gen") for p in (TESTS / package).rglob("*.py"))


@pytest.mark.parametrize("path", module_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_module_has_its_test_file_or_a_reason(path):
    relative = str(path.relative_to(ROOT))
    test_file = mirror_of(path)
    if relative in EXEMPT:
        assert not test_file.exists(), f"{relative} has {test_file.relative_to(ROOT)}: unlist it"
    else:
        assert test_file.is_file(), (
            f"add {test_file.relative_to(ROOT)}, or list {relative} in EXEMPT with the reason"
        )


def test_every_exemption_names_a_module():
    missing = [name for name in EXEMPT if not (ROOT / name).is_file()]
    assert not missing, f"EXEMPT names no module: {missing}"


@pytest.mark.parametrize("path", mirror_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_mirrored_test_file_names_a_module(path):
    """tests/<package>/test_<m>.py tests <package>/<m>.py (or _<m>.py): a test of no
    module, or a helper in a mirror folder (helpers go in tests/helpers), is refused."""
    relative = path.relative_to(TESTS)
    if path.name in MIRROR_EXTRAS:
        assert (ROOT / relative.parent / "__init__.py").is_file(), f"{relative.parent}: no package"
        return
    assert path.name.startswith("test_"), f"tests/{relative}: helpers go in tests/helpers/"
    name = path.stem.removeprefix("test_")
    folder = ROOT / relative.parent
    tested = [folder / f"{prefix}{name}.py" for prefix in ("", "_")]
    assert any(p.is_file() for p in tested), f"tests/{relative} mirrors no module"
    assert (path.parent / "__init__.py").is_file(), f"tests/{relative.parent} needs __init__.py"


def test_the_top_level_tests_are_the_checks_across_the_tree():
    found = sorted(p.name for p in TESTS.glob("test_*.py"))
    unlisted = [name for name in found if name not in ACROSS]
    assert not unlisted, f"move these to tests/<package>/test_<module>.py, or list them: {unlisted}"


def test_the_mirror_does_not_shadow_the_packages_it_tests():
    """tests/kpstudy and tests/data_gen are the packages tests.kpstudy and tests.data_gen:
    tests/ itself is never on sys.path, so ``import kpstudy`` finds the repository's."""
    import data_gen
    import kpstudy

    assert Path(kpstudy.__file__).resolve() == ROOT / "kpstudy" / "__init__.py"
    assert Path(data_gen.__file__).resolve() == ROOT / "data_gen" / "__init__.py"
    assert TESTS not in {Path(p or ".").resolve() for p in sys.path}
    assert __name__ == "tests.test_layout"
