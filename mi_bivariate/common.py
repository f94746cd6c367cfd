"""Small definitions every stage shares: the path type, luminance, JSON without NaN, file digests, where an
st map's cells are drawn.

This module imports nothing of the package, so any module may use it.
"""

from __future__ import annotations

import hashlib
import math
import os
from typing import Any, Tuple, Union

import numpy as np

#: A file-system path as users pass it: ``str`` or any ``os.PathLike``.
PathLike = Union[str, os.PathLike]

#: Rec. 709 luminance weights of linear RGB, as Mitsuba's ``luminance()``.
LUMINANCE_WEIGHTS = np.array([0.212671, 0.715160, 0.072169])


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance ``(...) float64`` of linear RGB ``(..., 3)``."""
    return np.asarray(rgb, dtype=np.float64) @ LUMINANCE_WEIGHTS


def finite_json(value: Any) -> Any:
    """``value`` (dicts, lists and numbers) with every non-finite number as ``None``: JSON has no words for
    NaN and +-Infinity (Python writes ``NaN``, which strict readers refuse), so an output file says
    ``null`` where a figure is undefined (e.g. Eq. 1 on observed cells when no cell is observed)."""
    if isinstance(value, dict):
        return {k: finite_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_json(v) for v in value]
    if isinstance(value, (float, np.floating)) and not math.isfinite(value):
        return None
    return value


def file_digest(path: "PathLike") -> str:
    """16 hex digits of SHA-256 over a file's bytes, read in blocks, or ``"missing"`` where it cannot be read:
    what decides a result keyed by a file (a prior, a MERL material), whatever its name or time stamp."""
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                digest.update(block)
    except OSError:
        return "missing"
    return digest.hexdigest()[:16]


def node_extent(n_t: int, n_s: int) -> Tuple[float, float, float, float]:
    """``imshow`` extent that centres each cell of an ``(n_t, n_s)`` st map on its node (s, t = i / (n - 1)).

    ``extent=(0, 1, 0, 1)`` centres cell i at (i + 0.5) / n instead: half a cell off at the edges
    (on 8 x 8, theta_h's second node, 1.8 degrees, was drawn at 3.2). Show it with limits 0..1.
    """
    ds, dt = 0.5 / max(n_s - 1, 1), 0.5 / max(n_t - 1, 1)
    return (-ds, 1.0 + ds, -dt, 1.0 + dt)
