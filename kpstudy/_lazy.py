"""Re-exports that import their module on first use (PEP 562).

A subpackage's ``__init__`` names its public objects by module; ``from kpstudy.pose import
solve_pnp`` then imports :mod:`kpstudy.pose.pnp` alone, and ``import kpstudy.pose.geometry``
costs what that module costs (not cvxpy for the allocation beside it), as before the
subpackages existed: the CLI, data_gen and every worker process start as fast.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
from collections.abc import Callable
from pathlib import Path


def lazy_exports(
    package: str, modules: dict[str, tuple[str, ...]]
) -> tuple[list[str], Callable[[str], object], Callable[[], list[str]]]:
    """``__all__``, ``__getattr__`` and ``__dir__`` for ``package`` that re-export
    ``modules`` (submodule name → its public names, or None: the submodule's own literal
    ``__all__``, read from its source without importing it, so the names stand in one
    place).

    Examples
    --------
    >>> all_, getattr_, dir_ = lazy_exports("kpstudy.pose", {"pnp": ("solve_pnp",)})
    >>> all_, getattr_("solve_pnp").__module__
    (['solve_pnp'], 'kpstudy.pose.pnp')
    """
    modules = {
        module: _source_all(package, module) if names is None else names
        for module, names in modules.items()
    }
    where = {name: module for module, names in modules.items() for name in names}
    if len(where) != sum(map(len, modules.values())):
        raise ValueError(f"modules: a name is exported twice in {package}")
    clash = set(where) & set(modules)
    if clash:
        raise ValueError(f"modules: {sorted(clash)} would shadow a module of {package}")

    def __getattr__(name: str):
        if name not in where:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{where[name]}"), name)
        setattr(importlib.import_module(package), name, value)
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(importlib.import_module(package))) | set(where))

    return sorted(where), __getattr__, __dir__


def _source_all(package: str, module: str) -> tuple[str, ...]:
    """The literal ``__all__`` of ``package.module``, from its source file."""
    path = Path(importlib.util.find_spec(package).submodule_search_locations[0], f"{module}.py")
    for node in ast.parse(path.read_text(encoding="utf-8")).body:
        if isinstance(node, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets
        ):
            return tuple(ast.literal_eval(node.value))
    raise ValueError(f"modules: {package}.{module} has no literal __all__ to re-export")
