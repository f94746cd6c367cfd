"""mi_bivariate: passive reflectometry with bivariate BRDFs for Mitsuba 3.

Submodules load on first use (``mi_bivariate.probes``, ``mi_bivariate.recover``,
...), so ``import mi_bivariate`` stays cheap and does not pick a Mitsuba
variant. ``mi_bivariate.recover`` is the module; its function of the same name
is the library's front door.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_SUBMODULES = (
    "adequacy", "alignment", "analytic", "atomic", "baselines", "basis_prior", "bivariate", "capture", "cli",
    "coordinates", "demo", "errors", "evaluate", "geometry", "images", "lighting", "merl", "mesh", "metrics",
    "nbrdf", "noise", "npzio", "prior", "probes", "recover", "reference", "render", "report", "solve",
    "spherefit", "synthesis", "threads", "training_set", "variants",
)


def __getattr__(name: str) -> Any:
    if name in _SUBMODULES:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list:
    return sorted(list(globals()) + list(_SUBMODULES))
