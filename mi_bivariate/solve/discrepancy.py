"""Choosing alpha: the discrepancy principle (Morozov 1966), bounded by the learnt alpha.

The smoothness prior's weight alpha (one for the three channels) is the largest alpha in
``[DISCREPANCY_ALPHAS[0], DISCREPANCY_ALPHAS[-1]]`` (``1e-4`` to :data:`DEFAULT_ALPHA`) whose
(unconstrained Tikhonov) solution still explains the image to within its expected error: the
data term ``rho(alpha) = (1/M) ||(I - L f_alpha) / sigma||^2`` (the mean over the channels) at
most :data:`DISCREPANCY_TARGET`. ``rho`` grows with alpha, so the answer is found on the log grid
:data:`DISCREPANCY_ALPHAS` (from the default alpha: its floor, then bisection),
then by regula falsi in ``(log alpha, log rho)`` inside the bracketing half decade
(:data:`REFINEMENTS` steps). An image the default explains costs one Cholesky factorisation
per channel; one that needs the floor (1e-4), two; one in between, five.

Why bounded above, and why a target of 20 and not 1 (measured on 16 *training* materials,
never on a scored one; ``docs/recovery.md``, "Choosing alpha"):

- The rows' ``sigma`` (:func:`~mi_bivariate.solve.row_sigma`) carries a model error of 1% of
  the pixel besides the camera's noise, but the bivariate reduction's own error in a pixel
  (what the isotropic 3D BRDF does that no (theta_h, theta_d) table can) is larger and varies
  from material to material: at the alpha that relit best, ``rho`` was 0.5 to 40. A target of
  1 would drive alpha to its floor for most materials; 20 (an expected error of ~4.5% of a
  pixel) leaves the default in place unless the image is clearly not explained.
- Where the default does not explain the image (``rho`` of 100-270 for a metallic paint), the
  image is right: lowering alpha until ``rho = 20`` relit it at 0.47x the exact reduction's
  error instead of 2.1x.
- The data term cannot see the nodes the image does not constrain, which are what novel
  light exposes: where ``rho`` is already small at the default, *raising* alpha to meet the
  target smoothed those nodes and relit 3 of the 6 training materials whose alpha it raised worse
  (up to 1.9x; docs/recovery.md section 4). The
  learnt alpha is therefore an upper bound, the prior's strength for what the image does not
  say; the image may only lower it.

With camera noise the rows' ``sigma`` grows and ``rho`` shrinks, so a noisy image keeps the
default (it is not over-fitted). GCV (:mod:`~mi_bivariate.solve.gcv`) estimates the error
level from the residual instead, and over-fits, because the model error is correlated between
neighbouring pixels.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, Optional, Sequence, Tuple

import numpy as np

from mi_bivariate.solve.common import DEFAULT_ALPHA, add_entries, penalty_weight, sparse_entries
from mi_bivariate.solve.data_term import DataTerm
from mi_bivariate.solve.lapack import cho_factor, cho_solve
from mi_bivariate.threads import thread_map

#: The log grid walked (half decades from 1e-4 to DEFAULT_ALPHA = 1e-2): the range alpha is chosen in.
DISCREPANCY_ALPHAS = tuple(10.0 ** np.arange(-4.0, -1.99, 0.5))
#: Regula falsi steps inside the bracketing half decade (one Cholesky factorisation each).
REFINEMENTS = 1
#: The data term (mean squared residual in units of the rows' sigma) alpha is raised to.
DISCREPANCY_TARGET = 20.0


@dataclass
class DiscrepancyChoice:
    """The discrepancy principle's alpha (one for the channels whose data terms were averaged)."""
    alpha: float            #: the chosen alpha
    alphas: np.ndarray      #: (A,) the alphas evaluated, ascending
    data_terms: np.ndarray  #: (A,) rho at each (unconstrained)
    #: "" (target met inside the range), "low" (rho > target at the smallest alpha) or "high"
    #: (rho <= target at the largest)
    bounded: str
    #: the channels' Cholesky factors of ``gram + lambda P [+ extra]`` at :attr:`alpha` when it was
    #: the last alpha evaluated (the constrained solve with the same prior starts from them and
    #: drops them), else ``None``
    factors: Optional[list] = field(default=None, repr=False, compare=False)


def _data_term(data: DataTerm, entries: tuple, channels: Sequence[int], alpha: float,
               extra: Optional[Tuple[np.ndarray, np.ndarray]]) -> Tuple[float, list]:
    """The mean over ``channels`` of the unconstrained solution's data term at ``alpha``
    (``entries``: the penalty's, :func:`~mi_bivariate.solve.common.sparse_entries`), and each
    channel's Cholesky factor of its system; the channels on worker threads
    (:func:`~mi_bivariate.threads.thread_map`)."""
    n = data.n_nodes

    def channel(k: int) -> Tuple[float, tuple]:
        g, b = data.gram[k], data.rhs[k]
        x = add_entries(g.copy(), entries, penalty_weight(alpha, n, data.level[k]))
        rhs = b
        if extra is not None:
            x[np.diag_indices(n)] += extra[0][:, k]
            rhs = b + extra[1][:, k]
        factor = cho_factor(x, overwrite=True)
        f = cho_solve(factor, rhs)
        return max(data.yy[k] - 2.0 * f @ b + f @ g @ f, 0.0), factor

    results = thread_map(channel, channels)
    return float(sum(r[0] for r in results) / len(channels)), [r[1] for r in results]


def discrepancy_alpha(data: DataTerm, penalty: np.ndarray, channels: Sequence[int] = (0, 1, 2),
                      target: float = DISCREPANCY_TARGET, alphas: Sequence[float] = DISCREPANCY_ALPHAS,
                      start: float = DEFAULT_ALPHA, extra: Optional[Tuple[np.ndarray, np.ndarray]] = None,
                      entries: Optional[tuple] = None, keep_factors: bool = False) -> DiscrepancyChoice:
    """The largest alpha with data term ``rho(alpha) <= target``, ``rho`` the mean over ``channels``.

    One alpha serves every channel: chosen per channel, a material's colour channels were
    smoothed by alphas three decades apart and relit worse (``docs/recovery.md``).

    Args:
        data: the normal equations (rows weighted by their sigma).
        penalty: ``(N, N)`` the prior's ``R^T R``.
        channels: which channels' data terms are averaged.
        target: the data term allowed (see the module's notes).
        alphas: ascending log grid bounding the choice; the search starts at the grid point
            nearest ``start``, tries the far end of the grid in the direction of the target,
            then bisects the grid between them.
        extra: ``(precision, shift)`` ``(N, 3)`` each: a fixed diagonal Gaussian term (the
            basis prior) in the system and the right-hand side.
        entries: ``penalty``'s non-zero entries if the caller has them
            (:func:`~mi_bivariate.solve.common.sparse_entries`).
        keep_factors: return the channels' factors at the chosen alpha when it was the last one
            evaluated (:attr:`DiscrepancyChoice.factors`; 3 ``N x N`` arrays for the caller to take).
    """
    grid = np.asarray(alphas, np.float64)
    seen: Dict[float, float] = {}  # alpha -> rho
    last: Dict[float, list] = {}   # the last alpha evaluated -> its factors (one alpha's at a time)
    entries = sparse_entries(penalty) if entries is None else entries

    def rho(alpha: float) -> float:
        if alpha not in seen:
            last.clear()
            seen[alpha], last[alpha] = _data_term(data, entries, channels, alpha, extra)
        return seen[alpha]

    def choice(alpha: float, bounded: str) -> DiscrepancyChoice:
        evaluated = np.array(sorted(seen))
        keep = keep_factors and list(channels) == [0, 1, 2]
        return DiscrepancyChoice(float(alpha), evaluated, np.array([seen[v] for v in evaluated]), bounded,
                                 last.get(float(alpha)) if keep else None)

    # From the start, the far end of the grid in the direction of the target first (often the
    # answer), then bisection of the grid between the last point below the target and the first above.
    i = int(np.argmin(np.abs(np.log(grid) - np.log(start))))
    if rho(grid[i]) <= target:
        lo, hi = i, len(grid) - 1
        if rho(grid[hi]) <= target:
            return choice(grid[hi], "high")
    else:
        lo, hi = 0, i
        if rho(grid[lo]) > target:
            return choice(grid[lo], "low")
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if rho(grid[mid]) <= target else (lo, mid)
    # Regula falsi in (log alpha, log rho) inside the bracket [grid[lo], grid[hi]].
    lo_pt = (np.log(grid[lo]), np.log(max(rho(grid[lo]), 1e-300)))
    hi_pt = (np.log(grid[hi]), np.log(rho(grid[hi])))
    y = np.log(target)

    def secant() -> float:
        (x0, y0), (x1, y1) = lo_pt, hi_pt
        return x0 if y1 <= y0 else float(np.clip(x0 + (y - y0) * (x1 - x0) / (y1 - y0), x0, x1))

    x = secant()
    for _ in range(REFINEMENTS):
        value = rho(float(np.exp(x)))
        point = (x, np.log(max(value, 1e-300)))
        lo_pt, hi_pt = (point, hi_pt) if value <= target else (lo_pt, point)
        x = secant()
    return choice(float(np.exp(x)), "")
