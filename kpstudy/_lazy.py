"""Re-exports that import their module on first use (PEP 562).

A subpackage's ``__init__`` names its public objects by module; ``from kpstudy.pose import
solve_pnp`` then imports :mod:`kpstudy.pose.pnp` alone, and ``import kpstudy.pose.geometry``
costs what that module costs (not cvxpy for the allocation beside it), as before the
subpackages existed: the CLI, data_gen and every worker process start as fast.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable


def lazy_exports(
    package: str, modules: dict[str, tuple[str, ...]]
) -> tuple[list[str], Callable[[str], object], Callable[[], list[str]]]:
    """``__all__``, ``__getattr__`` and ``__dir__`` for ``package`` that re-export
    ``modules`` (submodule name → its public names).

    Examples
    --------
    >>> all_, getattr_, dir_ = lazy_exports("kpstudy.pose", {"pnp": ("solve_pnp",)})
    >>> all_, getattr_("solve_pnp").__module__
    (['solve_pnp'], 'kpstudy.pose.pnp')
    """
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
