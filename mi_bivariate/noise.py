"""The camera noise model: variance ``a I + b`` (Poisson-Gaussian), estimated from an image.

A camera's raw noise is signal-dependent: photon shot noise grows with the signal
(``a I``), read noise does not (``b``). The solve weights every observation by
this model plus a relative model error (:func:`mi_bivariate.solve.row_sigma`), so
dim pixels count as much as their noise allows and noisy images are not
over-fitted.

:func:`estimate_camera_noise` finds ``(a, b)`` from one image of a smooth object:
second differences ``I[x-1] - 2 I[x] + I[x+1]`` along rows and columns cancel the
smooth signal up to its curvature and keep ``6 sigma^2`` of white noise; their
robust (low-quantile) variance per intensity bin, fitted by non-negative least
squares to ``a I + b``, is the estimate (the approach of Foi et al., "Practical
Poissonian-Gaussian noise modeling and fitting for single-image raw-data", IEEE
TIP 2008, in its simplest form).
"""

from __future__ import annotations

from typing import Optional, Tuple

import numpy as np
import scipy.optimize as sopt

from .errors import InputError

#: Intensity bins of the estimate (quantiles of the masked image).
BINS = 12
#: Quantile of ``d^2`` per bin that estimates the noise: low, so that the few pixels
#: whose second difference holds the signal's own curvature (the edges of sharp
#: highlights) do not count as noise.
QUANTILE = 0.25
#: That quantile of chi-square(1): ``var = quantile(d^2) / this`` for Gaussian ``d``.
_CHI2_QUANTILE = float(__import__("scipy.stats", fromlist=["chi2"]).chi2.ppf(QUANTILE, 1))


def _second_differences(image: np.ndarray, mask: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """``(level, d)``: centre value and second difference where all three pixels are in the mask."""
    levels, diffs = [], []
    for axis in (0, 1):
        a = np.moveaxis(image, axis, 0)
        m = np.moveaxis(mask, axis, 0)
        ok = m[:-2] & m[1:-1] & m[2:]
        d = a[:-2] - 2.0 * a[1:-1] + a[2:]
        levels.append(a[1:-1][ok])
        diffs.append(d[ok])
    return np.concatenate(levels), np.concatenate(diffs)


def estimate_camera_noise(image: np.ndarray, mask: Optional[np.ndarray] = None,
                          source: str = "image") -> Tuple[float, float]:
    """Poisson-Gaussian noise ``(a, b)`` of a linear image (variance ``a I + b``, image units).

    Args:
        image: ``(H, W)`` or ``(H, W, 3)`` linear values (channels are averaged).
        mask: ``(H, W) bool`` pixels of the object (default: every finite pixel).

    Raises:
        InputError: fewer than 100 usable pixels.
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim == 3:
        img = img.mean(axis=2)
    if img.ndim != 2:
        raise InputError(source, f"expected an (H, W) or (H, W, 3) image, got shape {np.shape(image)}")
    m = np.isfinite(img) if mask is None else (np.asarray(mask, bool) & np.isfinite(img))
    level, d = _second_differences(np.where(m, img, 0.0), m)
    if level.size < 100:
        raise InputError(source, f"only {level.size} usable pixels to estimate the noise from",
                         "give the noise model (a, b) explicitly")
    edges = np.unique(np.quantile(level, np.linspace(0.0, 1.0, BINS + 1)))
    centres, variances, counts = [], [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (level >= lo) & (level <= hi)
        if sel.sum() < 20:
            continue
        centres.append(float(np.median(level[sel])))
        variances.append(float(np.quantile(d[sel] ** 2, QUANTILE)) / _CHI2_QUANTILE / 6.0)
        counts.append(int(sel.sum()))
    if len(centres) == 1:  # a uniform image: no signal dependence to fit
        return 0.0, float(variances[0])
    if not centres:
        raise InputError(source, "the image is too uniform to estimate its noise", "give (a, b) explicitly")
    x = np.asarray(centres)
    w = np.sqrt(np.asarray(counts, np.float64)) / np.maximum(np.asarray(variances), 1e-300)
    design = np.stack([np.maximum(x, 0.0), np.ones_like(x)], axis=1) * w[:, None]
    (a, b), _ = sopt.nnls(design, np.asarray(variances) * w)
    return float(a), float(b)


def add_camera_noise(image: np.ndarray, a: float, b: float, seed: int = 0) -> np.ndarray:
    """``image`` plus seeded Gaussian noise of variance ``a I + b`` (image units), float32."""
    img = np.asarray(image, dtype=np.float64)
    if not (np.isfinite(a) and np.isfinite(b) and a >= 0 and b >= 0):
        raise InputError("noise", f"a and b must be finite and >= 0, got a={a}, b={b}")
    rng = np.random.default_rng(seed)
    sigma = np.sqrt(a * np.maximum(img, 0.0) + b)
    return (img + sigma * rng.standard_normal(img.shape)).astype(np.float32)
