"""mi_bivariate: passive reflectometry with bivariate BRDFs for Mitsuba 3.

Submodules load on first use (``mi_bivariate.probes``, ``mi_bivariate.recover``,
...), so ``import mi_bivariate`` stays cheap and does not pick a Mitsuba
variant. ``mi_bivariate.recover`` is the module; its function of the same name
is the library's front door.
"""

from __future__ import annotations

import importlib
import os

__version__ = "0.1.0"


def _on_disk(folder: str) -> tuple:
    """The modules (``*.py``) and sub-packages (folders with an ``__init__.py``) in ``folder``, private ones
    aside. A listing of the folder, not ``pkgutil.iter_modules``: that imports ``inspect`` (~10 ms), before
    the command line's Ctrl-C guard (``mi_bivariate.__main__``) is set up, where a Ctrl-C still ends in a
    traceback (a helper measured that window at 0.03-0.045 s of the console script's start)."""
    try:
        entries = list(os.scandir(folder))
    except OSError:  # not a folder (a zip archive, a frozen application): ask the import system
        import pkgutil

        return tuple(sorted(m.name for m in pkgutil.iter_modules([folder]) if not m.name.startswith("_")))
    names = []
    for entry in entries:
        stem = entry.name[:-3] if entry.name.endswith(".py") else entry.name
        if stem.startswith("_") or not stem.isidentifier():  # private, or no module name (.hidden.py, a.b.py)
            continue
        if entry.name.endswith(".py") and entry.is_file():
            names.append(stem)
        elif entry.is_dir() and os.path.isfile(os.path.join(entry.path, "__init__.py")):
            names.append(stem)
    return tuple(sorted(names))


#: Every module and sub-package of the package, found on disk so the list cannot drift.
_SUBMODULES = _on_disk(__path__[0])


def __getattr__(name: str) -> object:  # (no typing import: see _on_disk)
    if name in _SUBMODULES:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list:
    return sorted(list(globals()) + list(_SUBMODULES))
