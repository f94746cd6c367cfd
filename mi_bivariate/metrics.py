"""Error metrics for recovered BRDFs and re-rendered images (pure numpy).

BRDF errors compare a bivariate table against a 3D MERL table on the MERL
grid; see :func:`mi_bivariate.bivariate.reduction_error` for Eq. 1 itself.
"""

from __future__ import annotations

from typing import Optional

import numpy as np


def image_relative_rmse(image: np.ndarray, reference: np.ndarray, mask: Optional[np.ndarray] = None) -> float:
    """``||image - reference|| / ||reference||`` over masked pixels and all channels.

    Args:
        image, reference: ``(H, W, 3)`` linear images.
        mask: ``(H, W) bool``; all pixels when omitted.
    """
    a = np.asarray(image, dtype=np.float64)
    b = np.asarray(reference, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"image shapes differ: {a.shape} vs {b.shape}")
    if mask is not None:
        a, b = a[mask], b[mask]
    denom = np.sqrt(np.mean(b * b))
    return float(np.sqrt(np.mean((a - b) ** 2)) / denom) if denom > 0 else float("inf")


def image_psnr(image: np.ndarray, reference: np.ndarray, mask: Optional[np.ndarray] = None) -> float:
    """PSNR in dB with the reference's masked maximum as peak (linear radiance)."""
    a = np.asarray(image, dtype=np.float64)
    b = np.asarray(reference, dtype=np.float64)
    if mask is not None:
        a, b = a[mask], b[mask]
    mse = np.mean((a - b) ** 2)
    peak = float(np.max(b)) if b.size else 0.0
    if mse == 0:
        return float("inf")
    return float(10.0 * np.log10(peak * peak / mse)) if peak > 0 else float("-inf")
