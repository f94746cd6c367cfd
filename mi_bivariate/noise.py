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
"""

from __future__ import annotations

from typing import Optional, Tuple

import numpy as np

from mi_bivariate.errors import InputError

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
