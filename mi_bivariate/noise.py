"""Controlled camera noise for the inputs of the accuracy tables.

The inputs of the accuracy tables are clean by default (converged references,
:mod:`mi_bivariate.reference`). :func:`add_camera_noise` adds a stated,
seeded, signal-dependent noise, like a camera's shot plus read noise::

    I_noisy = I + sqrt(a I + b) z,    z ~ N(0, 1) independently per pixel and channel

with ``a = level^2 * I_ref`` and ``b = (level * I_ref / 10)^2``, where
``I_ref`` is the image's mean over its non-zero pixels (all channels) and
``level`` the relative standard deviation at ``I = I_ref``: shot noise gives
``level`` at the mean signal (``sqrt(a I_ref) / I_ref = level``), the read
noise floor is a tenth of that at the mean. ``level = 0.02`` is "2% noise at
the mean signal". Values stay as they come out (negative values are
possible, as in a camera's raw data after black-level subtraction); zero
pixels (background) stay zero.

:func:`estimate_camera_noise` goes the other way: it finds ``(a, b)`` from one
image of a smooth object, for the solve's noise-aware data term
(:func:`mi_bivariate.solve.row_sigma`). Second differences
``I[x-1] - 2 I[x] + I[x+1]`` along rows and columns cancel the smooth signal up to
its curvature and keep ``6 sigma^2`` of white noise; their robust (low-quantile)
variance per intensity bin, fitted by non-negative least squares to ``a I + b``
(:func:`nonnegative_fit`),
is the estimate (the approach of Foi et al., "Practical Poissonian-Gaussian noise
modeling and fitting for single-image raw-data", IEEE TIP 2008, in its simplest
form). Measured on path-traced spheres it *under*-estimates heavy-tailed Monte
Carlo noise (by 4-50x in the brightest bins); on camera-like Gaussian noise it is
within 25% (tests/test_noise.py).
"""

from __future__ import annotations

from statistics import NormalDist
from typing import Optional, Tuple, Union

import numpy as np

from mi_bivariate.errors import InputError
from mi_bivariate.images import bounding_box

#: Intensity bins of the estimate (quantiles of the masked image).
BINS = 12
#: Fewest second differences a bin needs to count (fewer: too few for its quantile).
MIN_BIN_PIXELS = 20
#: Quantile of ``d^2`` per bin that estimates the noise: low, so that the few pixels
#: whose second difference holds the signal's own curvature (the edges of sharp
#: highlights) do not count as noise.
QUANTILE = 0.25
#: That quantile of chi-square(1), ``z^2`` for the standard normal's ``(1 + q) / 2`` quantile ``z`` (what
#: ``scipy.stats.chi2.ppf(q, 1)`` gives, without importing scipy.stats or scipy.special, which a
#: command defers: :func:`mi_bivariate.process.defer_unused_modules`): ``var = quantile(d^2) / this``
#: for Gaussian ``d``.
_CHI2_QUANTILE = NormalDist().inv_cdf(0.5 + 0.5 * QUANTILE) ** 2


#: Most second differences an estimate uses: a larger object's are taken along every ``k``-th row and column
#: (:func:`_second_differences`), ~40 k per intensity bin, enough for its quantile to ~1%. Measured on a
#: 2048 x 2048 photo (2-core VM): the estimate took 0.86 s per channel from its 5.3 M differences.
MAX_SECOND_DIFFERENCES = 2**19


def _second_differences(image: np.ndarray, mask: np.ndarray, step: int = 1) -> Tuple[np.ndarray, np.ndarray]:
    """``(level, d)`` in float64: centre value and second difference where all three pixels are in the mask,
    along every ``step``-th column (differences down the columns) and row (along the rows) of the ``(H, W)``
    image (converted there only)."""
    levels, diffs = [], []
    for axis in (0, 1):
        a = np.asarray(np.moveaxis(image, axis, 0)[:, ::step], np.float64)  # the sampled lines only
        m = np.moveaxis(mask, axis, 0)[:, ::step]
        ok = m[:-2] & m[1:-1] & m[2:]
        with np.errstate(invalid="ignore", over="ignore"):  # pixels outside the mask may be anything
            d = a[:-2] - 2.0 * a[1:-1] + a[2:]
        levels.append(a[1:-1][ok])
        diffs.append(d[ok])
    return np.concatenate(levels), np.concatenate(diffs)


def estimate_camera_noise(image: np.ndarray, mask: Optional[np.ndarray] = None,
                          source: str = "image") -> Tuple[float, float]:
    """Poisson-Gaussian noise ``(a, b)`` of a linear image (variance ``a I + b``, image units).

    Args:
        image: ``(H, W)`` or ``(H, W, 3)`` linear values (channels are averaged).
        mask: ``(H, W) bool`` pixels of the object (default: every finite pixel); non-finite pixels in it
            are left out. An object of more than :data:`MAX_SECOND_DIFFERENCES` / 2 pixels is sampled along
            every ``k``-th row and column, ``k`` odd, counted from the mask's first row and column (so that
            the estimate does not depend on where the object sits in the frame). The work is done within
            the mask's box.

    Raises:
        InputError: another shape, or too few usable pixels: fewer than 100 second differences, or fewer
            than :data:`MIN_BIN_PIXELS` in each intensity bin.
    """
    img = np.asarray(image)
    if not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)):
        raise InputError(source, f"expected an (H, W) or (H, W, 3) image, got shape {np.shape(image)}")
    if mask is not None:
        mask = np.asarray(mask, bool)
        if mask.shape != img.shape[:2]:
            raise InputError(source, f"the noise estimate's mask has shape {mask.shape}, the image {img.shape}",
                             "give an (H, W) boolean mask of the image's size")
        rows, cols = bounding_box(mask)
        img, mask = img[rows, cols], mask[rows, cols]
    if img.ndim == 3:
        img = np.asarray(img, dtype=np.float64).mean(axis=2)
    elif not np.issubdtype(img.dtype, np.floating):
        img = np.asarray(img, dtype=np.float64)
    m = np.isfinite(img) if mask is None else (mask & np.isfinite(img))
    # Each pixel inside the object gives up to two differences; a large object's are thinned evenly, by an
    # odd step: an even one keeps one phase of a noise that alternates with the Bayer pattern of a
    # demosaiced photo (measured: 0.56x the full estimate with step 2).
    step = max(1, -(-2 * int(np.count_nonzero(m)) // MAX_SECOND_DIFFERENCES)) | 1
    level, d = _second_differences(img, m, step)
    if level.size < 100:
        raise InputError(source, f"only {level.size} usable pixels to estimate the noise from",
                         "give the noise model (a, b) explicitly")
    edges = np.unique(np.quantile(level, np.linspace(0.0, 1.0, BINS + 1)))
    if len(edges) < 2:  # a uniform image: no signal dependence to fit
        return 0.0, float(np.quantile(d**2, QUANTILE)) / _CHI2_QUANTILE / 6.0
    centres, variances, counts = [], [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (level >= lo) & (level <= hi)
        if sel.sum() < MIN_BIN_PIXELS:
            continue
        centres.append(float(np.median(level[sel])))
        variances.append(float(np.quantile(d[sel] ** 2, QUANTILE)) / _CHI2_QUANTILE / 6.0)
        counts.append(int(sel.sum()))
    if len(centres) == 1:  # a uniform image: no signal dependence to fit
        return 0.0, float(variances[0])
    if not centres:  # quantile bins: only when there are fewer than BINS * MIN_BIN_PIXELS pixels
        raise InputError(source, f"only {level.size} usable pixels to estimate the noise from (fewer than "
                         f"{MIN_BIN_PIXELS} in each of its intensity bins)", "give the noise model (a, b) explicitly")
    x = np.asarray(centres)
    w = np.sqrt(np.asarray(counts, np.float64)) / np.maximum(np.asarray(variances), 1e-300)
    design = np.stack([np.maximum(x, 0.0), np.ones_like(x)], axis=1) * w[:, None]
    return nonnegative_fit(design, np.asarray(variances) * w)


def nonnegative_fit(design: np.ndarray, target: np.ndarray) -> Tuple[float, float]:
    """Non-negative least squares of two unknowns: ``argmin ||design x - target||`` over ``x >= 0``.

    The solution lies on one face of the constraints: both unknowns free, or one of them at zero (or
    both: the one-unknown fits clipped at zero). Each face's own least-squares fit that is feasible is a
    candidate, and the candidate with the smallest residual is the solution (what
    ``scipy.optimize.nnls`` returns, without importing ``scipy.optimize``, which costs a ``recover``
    process ~0.09 s of imports, bytecode compiled, for ~30 solvers it does not use;
    ``tests/test_noise.py`` compares the two). The columns and the target are first scaled by their
    largest magnitudes (a positive scaling keeps the constraints): the estimate's columns differ by the image's scale, 1e20 for a very bright image.

    Args:
        design: ``(n, 2)`` finite float64.
        target: ``(n,)`` finite float64.

    Returns:
        ``(x0, x1)``, both >= 0.
    """
    a = np.asarray(design, dtype=np.float64)
    y = np.asarray(target, dtype=np.float64)
    column_scale = np.max(np.abs(a), axis=0)
    column_scale = np.where(column_scale > 0, column_scale, 1.0)
    target_scale = float(np.max(np.abs(y)))
    if not target_scale > 0:
        return 0.0, 0.0
    a, y = a / column_scale, y / target_scale
    candidates = []
    for k in (0, 1):  # one unknown free, the other at zero (or both at zero: the clip)
        norm2 = float(a[:, k] @ a[:, k])
        x = np.zeros(2)
        x[k] = max(0.0, float(a[:, k] @ y) / norm2) if norm2 > 0 else 0.0
        candidates.append(x)
    both = np.linalg.lstsq(a, y, rcond=None)[0]
    if np.all(both >= 0):
        candidates.append(both)
    best = min(candidates, key=lambda x: float(np.sum((a @ x - y) ** 2))) * target_scale / column_scale
    return float(best[0]), float(best[1])


def check_noise_model(value, source: str = "noise") -> Tuple[Union[float, np.ndarray], Union[float, np.ndarray]]:
    """One camera-noise model ``(a, b)`` of the variance ``a I + b`` (image units), each a number or a
    per-channel ``(3,)`` sequence, finite and ``>= 0``: returned in the form given, each a float or a
    ``(3,)`` float64 array (both broadcast against ``(M, 3)`` rows; a recovery records the model as given).

    Raises:
        InputError: naming ``source``, for anything else (a string, one number, three entries, a
            ``(2,)`` per-channel array, NaN, a negative value).
    """
    hint = "give the pair (a, b) of the variance a I + b, each a number or three (R, G, B), e.g. (0, sigma**2)"
    if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple, np.ndarray)) \
            or (isinstance(value, np.ndarray) and value.ndim == 0) or len(value) != 2:  # a 0-d array: no len()
        raise InputError(source, f"expected the noise model (a, b), got {value!r}", hint)
    pair = []
    for v in value:
        if isinstance(v, (str, bytes)):
            raise InputError(source, f"expected the noise model (a, b) of numbers, got {value!r}", hint)
        try:
            x = np.asarray(v, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(source, f"expected the noise model (a, b) of numbers, got {value!r}", hint) from None
        if x.ndim > 1 or (x.ndim == 1 and len(x) != 3):
            raise InputError(source, f"a and b must each be a number or three (R, G, B), got {value!r}", hint)
        pair.append(float(x) if x.ndim == 0 else x.copy())
    a, b = pair
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b)) and np.all(a >= 0) and np.all(b >= 0)):
        raise InputError(source, f"camera noise (a, b) must be finite and >= 0, got {value!r}", hint)
    return a, b


#: Read-noise standard deviation as a fraction of the shot noise at the mean signal.
READ_FRACTION = 0.1


def noise_parameters(image: np.ndarray, level: float) -> Tuple[float, float]:
    """``(a, b)`` of the variance ``a I + b`` for ``level`` (see the module docstring)."""
    img = np.asarray(image, np.float64)
    signal = img[img > 0]
    ref = float(signal.mean()) if signal.size else 0.0
    level = float(level)
    return level * level * ref, (READ_FRACTION * level * ref) ** 2


def add_camera_noise(image: np.ndarray, level: float, seed: int = 0,
                     mask: Optional[np.ndarray] = None) -> np.ndarray:
    """The image plus seeded noise of variance ``a I + b`` (module docstring); float32 copy.

    Args:
        image: ``(H, W, 3)`` linear radiance.
        level: relative noise at the image's mean signal (0 returns a copy).
        seed: the noise is a function of ``(image, level, seed)`` only.
        mask: ``(H, W) bool`` pixels that get noise (default: pixels with any non-zero channel).
    """
    img = np.asarray(image, np.float64)
    if not (np.isfinite(level) and level >= 0.0):
        raise InputError("--noise", f"noise level must be a finite number >= 0, got {level}")
    if level == 0.0:
        return np.asarray(image, np.float32).copy()
    a, b = noise_parameters(img, level)
    if mask is None:
        mask = np.any(img != 0.0, axis=-1)
    z = np.random.default_rng(int(seed)).standard_normal(img.shape)
    sigma = np.sqrt(np.maximum(a * np.maximum(img, 0.0) + b, 0.0))
    out = np.where(np.asarray(mask, bool)[..., None], img + sigma * z, img)
    return out.astype(np.float32)
