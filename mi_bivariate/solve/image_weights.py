"""Several images weighted by how well each one's table predicts the others (leave one image out)."""

from __future__ import annotations

from typing import Any, Optional

import numpy as np

from mi_bivariate.basis_prior import BasisPrior
from mi_bivariate.limits import check_table_level
from mi_bivariate.prior import Prior
from mi_bivariate.solve.data_term import prepare_data_term
from mi_bivariate.solve.evidence import DEFAULT_PAIR_RULE
from mi_bivariate.solve.stages import solve_stages

#: How several images' rows are weighted beyond their own scale and noise (:func:`mi_bivariate.recover.recover`).
IMAGE_WEIGHTS = ("cross", "equal")
#: The smallest cross-prediction excess :func:`cross_image_factors` divides by (relative: 0.1%,
#: below the lighting matrix's own quadrature error, so nothing real is finer).
CROSS_FLOOR = 1e-3


def cross_image_factors(L: np.ndarray, values: np.ndarray, image_index: np.ndarray, sigma: np.ndarray,
                        prior: Prior, alpha: Any = None, basis: Optional[BasisPrior] = None,
                        pair_rule: str = DEFAULT_PAIR_RULE) -> np.ndarray:
    """``(max(image_index) + 1,) >= 1``: each image's sigma factor, by leave-one-image-out prediction
    (1 for an image without rows).

    Each image is solved alone (:func:`solve_stages`), and its table predicts the rows of
    every other image. What counts is how much worse image ``i``'s table predicts image ``j``
    than ``j``'s own noise allows: ``d_ij^2 = (||L_j f_i - I_j||^2 - s_j^2) / ||I_j||^2`` (0 if
    negative), with ``s_j^2 = RSS_j M_j / (M_j - dof_j)`` per channel, ``j``'s own residual with
    the degrees of freedom its fit used given back (the trace of its model resolution matrix), and
    ``d_i`` is the RMS over ``j`` of ``d_ij``. Image ``i``'s rows get their sigma multiplied by
    ``d_i / min d`` (``min d`` at least :data:`CROSS_FLOOR`): the image whose table carries
    over best to other light keeps its weight; one whose table does not (the bivariate model
    fitted to its lighting in ways no other image confirms) counts less. Relative errors: an
    image's brightness changes nothing. Costs one extra solve per image.

    Measured on training materials (``benchmarks/image_weight.py``, ``docs/recovery.md``
    section 4c): with grace_latlong_1k + uffizi_256, uffizi's rows weighed too much; these
    weights (uffizi's factor 1.5-10) relit 14 of 15 better than equal ones.

    Args:
        L: ``(M, N, 3)``; values: ``(M, 3)``; image_index: ``(M,)`` int; sigma: ``(M, 3)`` the rows'
            noise. prior, alpha, basis, pair_rule: as :func:`solve_stages`.
    """
    index = np.asarray(image_index, np.int64)
    images = np.unique(index)
    factors = np.ones(int(index.max()) + 1 if index.size else 0)
    if len(images) < 2:
        return factors
    rows_of = [index == i for i in images]
    L_of = [L[rows] for rows in rows_of]  # one copy of each image's rows, used by both loops
    observed_of = [values[rows].astype(np.float64) for rows in rows_of]
    tables, dof = [], []
    for i, rows, L_i, observed in zip(images, rows_of, L_of, observed_of):
        data = prepare_data_term(L_i, observed, sigma[rows])
        check_table_level(data.level, f"image {int(i)}")  # before its solve (these precede recover's own check)
        result = solve_stages(data, prior, alpha, basis, pair_rule)
        tables.append(result.table.reshape(-1, 3).astype(np.float32))
        dof.append(np.sum(result.resolution.reshape(-1, 3), axis=0))  # trace of the hat matrix per channel
    # misfit[a, b]: ||L_b f_a - I_b||^2 / ||I_b||^2, table of image a on the rows of image b;
    # floor[b]: image b's own misfit with its degrees of freedom given back, RSS M / (M - dof)
    # per channel (an image whose rows pin few nodes fits its own noise: its RSS under-states it).
    misfit = np.empty((len(images), len(images)))
    floor = np.empty(len(images))
    for b, (L_b, observed) in enumerate(zip(L_of, observed_of)):
        norm2 = max(float(np.sum(observed**2)), 1e-300)
        for a, table in enumerate(tables):
            predicted = np.einsum("mnc,nc->mc", L_b, table, optimize=True).astype(np.float64)
            rss = np.sum((predicted - observed) ** 2, axis=0)
            misfit[a, b] = float(rss.sum()) / norm2
            if a == b:
                m = float(len(observed))
                floor[b] = float(np.sum(rss * m / np.maximum(m - dof[b], 1.0))) / norm2
    excess = np.maximum(misfit - floor[None, :], 0.0)
    off = ~np.eye(len(images), dtype=bool)
    d = np.sqrt(np.array([excess[a][off[a]].mean() for a in range(len(images))]))
    if np.all(np.isfinite(d)):
        factors[images] = d / max(float(d.min()), CROSS_FLOOR)
        factors[images] = np.maximum(factors[images], 1.0)
    return factors
