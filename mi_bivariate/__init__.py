"""mi_bivariate: passive reflectometry with bivariate BRDFs for Mitsuba 3.

Submodules load on first use (``mi_bivariate.probes``, ``mi_bivariate.recover``,
...), so ``import mi_bivariate`` stays cheap and does not pick a Mitsuba
variant. ``mi_bivariate.recover`` is the module; its function of the same name
is the library's front door.
"""

from __future__ import annotations

import importlib
import pkgutil
from typing import Any

__version__ = "0.1.0"

#: Every module and sub-package of the package, found on disk so the list cannot drift.
_SUBMODULES = tuple(sorted(m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_")))


def __getattr__(name: str) -> Any:
    if name in _SUBMODULES:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list:
    return sorted(list(globals()) + list(_SUBMODULES))
