"""Mitsuba variant selection and plugin registration.

The toolkit runs on ``llvm_ad_rgb`` by default and on ``cuda_ad_rgb`` where a
GPU exists (same code). ``MI_BIVARIATE_VARIANT`` overrides the default. Python
BSDF plugins are registered per variant, so every switch goes through
:func:`ensure_variant`.

Only the front doors select the variant: the CLI's commands,
:func:`mi_bivariate.recover.recover`, the lighting matrices
(:func:`mi_bivariate.lighting.lighting_matrix`, ``texel_lighting_matrix``: they need a JIT
variant and switch an active ``scalar_rgb`` to the default), the rendering entry points
(``render``, including ``render.render_mesh``, and ``reference``), the demo and the
evaluation's workers. Code below them (data-model methods such as
``BivariateBRDF.to_bitmap`` or ``Probe.emitter``) uses whatever variant is
selected and never changes it; without one, Mitsuba itself raises
``No variant was set!``.

A variant's start imports Mitsuba's Python AD integrators (``prb``, ``prb_basic``,
``prbvolpath``, ...), whose ``@dr.syntax`` methods Dr.Jit rewrites from their source at
definition (``inspect.getsource``, ``ast``, ``compile``): ~0.1 s of a one-core start that a
recovery, which renders nothing, never uses. :func:`ensure_variant` has the rewrite happen on
each method's first call instead: the same rewritten code, run the
same way, paid only by the process that renders with that integrator
(:func:`mi_bivariate.process.syntax_on_first_call`).
"""

from __future__ import annotations

import os
from typing import Optional

import mitsuba as mi

from mi_bivariate.atomic import signals_deferred
from mi_bivariate.errors import InputError
from mi_bivariate.plugins import register
from mi_bivariate.process import syntax_on_first_call

DEFAULT_VARIANT = "llvm_ad_rgb"
SUPPORTED_VARIANTS = ("llvm_ad_rgb", "cuda_ad_rgb", "scalar_rgb")


def ensure_variant(variant: Optional[str] = None, vectorised: bool = False) -> str:
    """Select a Mitsuba variant (if needed) and register the plugins for it.

    Args:
        variant: a variant name; ``None`` keeps an already selected supported
            variant, else uses ``$MI_BIVARIATE_VARIANT`` or ``llvm_ad_rgb``.
        vectorised: the caller needs a JIT (wide) variant, as the lighting
            matrix does: with ``variant=None`` an active ``scalar_rgb`` is
            replaced by the default; naming ``scalar_rgb`` is an error.

    Returns:
        The active variant name.

    Raises:
        InputError: (a ``ValueError``) naming ``--variant`` or
            ``MI_BIVARIATE_VARIANT`` for an unsupported or unavailable variant.
    """
    current = mi.variant()
    source = "--variant"
    if variant is None:
        if current in SUPPORTED_VARIANTS and not (vectorised and current == "scalar_rgb"):
            variant = current
        else:
            variant = os.environ.get("MI_BIVARIATE_VARIANT") or DEFAULT_VARIANT
            source = "MI_BIVARIATE_VARIANT" if os.environ.get("MI_BIVARIATE_VARIANT") else "default variant"
    choices = [v for v in SUPPORTED_VARIANTS if not (vectorised and v == "scalar_rgb")]
    if variant not in choices:
        raise InputError(source, f"unsupported Mitsuba variant {variant!r}", f"use one of {', '.join(choices)}")
    if variant not in mi.variants():
        raise InputError(source, f"Mitsuba variant {variant!r} is not available in this build",
                         f"available: {', '.join(v for v in mi.variants() if v in choices)}")
    # A stop (mi_bivariate.atomic.stop_on_signal) raised inside the variant's start was said as the variant
    # failing to start: it waits for the start to end.
    with signals_deferred():
        if current != variant:
            try:
                with syntax_on_first_call():
                    mi.set_variant(variant)
            except (ImportError, RuntimeError) as exc:  # e.g. cuda_ad_rgb without a usable GPU or driver
                reason = " ".join(str(exc).split())[:200] or type(exc).__name__
                fallback = [v for v in ("llvm_ad_rgb", "scalar_rgb") if v in choices and v != variant][:1]
                raise InputError(source, f"Mitsuba variant {variant!r} cannot start on this machine ({reason})",
                                 f"use {fallback[0]}" if fallback else "use another variant") from None
        register()
    return variant

