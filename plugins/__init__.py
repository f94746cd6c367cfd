"""Mitsuba BSDF plugins of mi_bivariate: ``bivariate`` and ``merl``.

Python BSDF classes derive from the active variant's ``mi.BSDF``, and Mitsuba
keeps a plugin registry per variant, so :func:`register` builds the classes
for the current variant and registers them once per variant. Call it (or
:func:`mi_bivariate.variants.ensure_variant`, which does) after every
``mi.set_variant``.
"""

from __future__ import annotations

from typing import Dict, Set

import mitsuba as mi

from mi_bivariate.plugins.bivariate import make_bivariate_bsdf
from mi_bivariate.plugins.merl import make_merl_bsdf

# variant -> {plugin name: class}
_CLASSES: Dict[str, Dict[str, type]] = {}
# the variants whose plugin registry has them
_REGISTERED: Set[str] = set()


def plugin_classes() -> Dict[str, type]:
    """The plugin classes of the active variant (built on first use)."""
    variant = mi.variant()
    if variant is None:
        raise RuntimeError("set a Mitsuba variant (mi_bivariate.variants.ensure_variant()) before using the plugins")
    if variant not in _CLASSES:
        _CLASSES[variant] = {"bivariate": make_bivariate_bsdf(), "merl": make_merl_bsdf()}
    return _CLASSES[variant]


def register() -> None:
    """Register the ``bivariate`` and ``merl`` BSDFs with the active variant (idempotent)."""
    classes = plugin_classes()  # checks that a variant is set
    variant = mi.variant()
    if variant not in _REGISTERED:
        for name, cls in classes.items():
            mi.register_bsdf(name, lambda props, cls=cls: cls(props))
        _REGISTERED.add(variant)
