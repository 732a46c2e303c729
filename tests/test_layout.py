"""The package tree follows the pipeline: each part of kpstudy imports only the parts before
it (docs/design.md §2, "What each part may import"). Every import of every module of
kpstudy and data_gen counts, function-level ones included, read with ``ast`` (nothing is
imported)."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
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


def test_a_re_export_reads_the_modules_own_list_or_refuses():
    import pytest

    from kpstudy._lazy import lazy_exports
    from kpstudy.pose import allocation

    names, getattr_, _ = lazy_exports("kpstudy.pose", {"allocation": None})
    assert names == sorted(allocation.__all__)
    assert getattr_("allocate_tolerances") is allocation.allocate_tolerances
    with pytest.raises(ValueError, match=r"^modules: kpstudy.pose.pnp has no literal __all__"):
        lazy_exports("kpstudy.pose", {"pnp": None})
