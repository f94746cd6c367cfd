"""The data term of Eq. 6: noise-weighted rows and their normal equations.

``(1/M) ||(I_k - L_k f) / sigma_k||^2`` per colour channel k, with ``sigma`` each
observation's noise standard deviation (:func:`row_sigma`): a relative model error
every prediction carries plus the camera's ``a I + b``. Rows are thus weighted by
information, not brightness. :func:`prepare_data_term` builds the normal equations
once (float64, ``N x N`` per channel); every prior variant, alpha and stage of the
solve reuses them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np

from mi_bivariate.errors import InputError
from mi_bivariate.lighting.gram import weighted_gram
from mi_bivariate.noise import check_noise_model
from mi_bivariate.solve.common import validate_problem
from mi_bivariate.threads import thread_map

#: Relative error of one pixel's model prediction ``L f`` even for noise-free input
#: (a 3D BRDF is not bivariate: the exact phi_d average predicts MERL-NBRDF pixels to
#: ~1-5%; the lighting matrix's quadrature adds ~0.1%). It is the floor of every
#: row's noise: without it a clean image would have no noise scale at all.
MODEL_ERROR = 0.01
#: Pixels darker than this fraction of their image's mean (per channel) count as this
#: bright in the model-error term, so black pixels keep a finite weight.
DARK_FRACTION = 0.01
#: How the model error's variance grows with the pixel value ``I`` (``Ibar``: the
#: image's mean): ``"constant"`` ``(c Ibar)^2`` (each image normalised by its own
#: scale, unweighted within it), ``"sqrt"`` ``c^2 Ibar I`` (the default), ``"relative"``
#: ``(c I)^2``. Chosen on the 50 training materials, never on scored ones
#: (``docs/recovery.md``): relight/floor medians 1.3 ("sqrt", alpha 1e-2), 1.5
#: ("relative"), 1.25-1.45 ("constant", alpha 0.1-0.01).
MODEL_ERROR_FORMS = ("sqrt", "constant", "relative")


def row_sigma(I: np.ndarray, image_index: Optional[np.ndarray] = None,
              noise: Optional[Sequence[Optional[Tuple[float, float]]]] = None,
              model_error: float = MODEL_ERROR, form: str = "sqrt") -> np.ndarray:
    """Per-row noise standard deviation ``(M, 3) float64`` of the data term.

    ``sigma_m^2 = model(I_m) + a I_m + b``: the model error every observation carries
    (:data:`MODEL_ERROR_FORMS`, with ``I`` raised to at least ``d Ibar``) plus the
    camera's signal-dependent noise ``a I + b`` (Poisson-Gaussian, in the image's own
    units; :mod:`mi_bivariate.noise`). ``Ibar`` is the mean of the row's image in that
    channel and ``d`` is :data:`DARK_FRACTION`. Every image is thus weighted by its
    own scale and noise: multiplying an image (and its probe) by 50 multiplies its
    sigmas by 50 (with ``a``, ``b`` given in its units) and leaves the solve unchanged.

    Args:
        I: ``(M, 3)`` observed values.
        image_index: ``(M,)`` which image each row comes from (default: one image).
        noise: per image, ``(a, b)`` (scalars or per-channel ``(3,)``) or ``None``
            (no camera noise: clean input).
        model_error: ``c``.
        form: one of :data:`MODEL_ERROR_FORMS`.
    """
    if form not in MODEL_ERROR_FORMS:
        raise InputError("noise", f"unknown model-error form {form!r}", f"use one of {MODEL_ERROR_FORMS}")
    I = np.asarray(I, dtype=np.float64)
    index = np.zeros(len(I), dtype=np.int64) if image_index is None else np.asarray(image_index, np.int64)
    sigma2 = np.empty_like(I)
    for k in np.unique(index):
        rows = index == k
        values = np.maximum(I[rows], 0.0)
        mean = values.mean(axis=0)
        mean = np.where(mean > 0, mean, 1.0)
        level = np.maximum(values, DARK_FRACTION * mean)
        if form == "sqrt":
            var = model_error**2 * mean * level
        elif form == "relative":
            var = (model_error * level) ** 2
        else:
            var = np.broadcast_to((model_error * mean) ** 2, level.shape).copy()
        params = None if noise is None else noise[int(k)] if int(k) < len(noise) else None
        if params is not None:
            a, b = check_noise_model(params)
            var = var + a * values + b
        sigma2[rows] = var
    return np.sqrt(sigma2)


@dataclass
class DataTerm:
    """Noise-weighted normal equations of the data term, per channel (reusable across
    priors and alphas, e.g. for :func:`alpha_sweep`).

    With ``A = diag(1/sigma) L / sqrt(M)`` and ``y = I / (sigma sqrt(M))``:
    ``gram = A^T A`` and ``rhs = A^T y``, so ``(1/M) ||(I - L f)/sigma||^2 =
    f^T gram f - 2 rhs^T f + yy``.
    """
    gram: np.ndarray        #: (3, N, N) float64
    rhs: np.ndarray         #: (3, N) float64
    yy: np.ndarray          #: (3,) ||y||^2
    level: np.ndarray       #: (3,) 1/sr, the Lambertian (best constant) fit: the prior's scale
    sigma: np.ndarray       #: (M, 3) the rows' noise std (image units)
    lighting: np.ndarray    #: (M, N, 3) the caller's L (not copied)
    observations: np.ndarray  #: (M, 3) the caller's I (not copied)
    time_s: float = 0.0

    @property
    def n_rows(self) -> int:
        return self.lighting.shape[0]

    @property
    def n_nodes(self) -> int:
        return self.lighting.shape[1]

    @property
    def scale(self) -> np.ndarray:
        """(3,) the prior's scale, :attr:`level` (kept under its old name)."""
        return self.level


def prepare_data_term(L: np.ndarray, I: np.ndarray, sigma: Optional[np.ndarray] = None,
                      image_index: Optional[np.ndarray] = None) -> DataTerm:
    """Validate ``L (M, N, 3)`` and ``I (M, 3)`` and build the noise-weighted normal equations.

    Args:
        sigma: ``(M, 3)`` per-row noise std; default :func:`row_sigma` of ``I``
            (clean input: the model error alone), per image when ``image_index`` is given.
    """
    L, I = validate_problem(L, I)
    start = time.perf_counter()
    m, n = L.shape[:2]
    sigma = row_sigma(I, image_index) if sigma is None else np.asarray(sigma, dtype=np.float64)
    if sigma.shape != I.shape or not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
        raise InputError("noise", f"row sigmas must be finite, > 0 and shaped {I.shape}")
    gram = np.empty((3, n, n))
    rhs = np.empty((3, n))
    yy = np.empty(3)
    level = np.empty(3)
    ones = np.ones(n)

    def channel(k: int) -> None:
        w = 1.0 / (sigma[:, k] * np.sqrt(m))
        y_k = I[:, k].astype(np.float64) * w
        # By blocks of rows over the st nodes they touch (lighting.gram): ~1/6 of the dense flops.
        gram[k], rhs[k] = weighted_gram(L[:, :, k], w, y_k)
        yy[k] = y_k @ y_k

    thread_map(channel, range(3))  # the channels' products release the GIL (mi_bivariate.threads)
    for k in range(3):
        if not np.any(np.diag(gram[k]) > 0):
            raise InputError("lighting matrix L", f"channel {k} is all zero: the probe sheds no light in it",
                             "give a probe with light in every colour channel")
        level[k] = max(0.0, float(ones @ rhs[k]) / float(ones @ gram[k] @ ones))
    return DataTerm(gram, rhs, yy, level, sigma, L, I, time.perf_counter() - start)
