"""Small definitions every stage shares: the path type and luminance.

This module imports nothing of the package, so any module may use it.
"""

from __future__ import annotations

import os
from typing import Union

import numpy as np

#: A file-system path as users pass it: ``str`` or any ``os.PathLike``.
PathLike = Union[str, os.PathLike]

#: Rec. 709 luminance weights of linear RGB, as Mitsuba's ``luminance()``.
LUMINANCE_WEIGHTS = np.array([0.212671, 0.715160, 0.072169])


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance ``(...) float64`` of linear RGB ``(..., 3)``."""
    return np.asarray(rgb, dtype=np.float64) @ LUMINANCE_WEIGHTS
