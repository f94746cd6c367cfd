"""Choosing alpha: generalised cross-validation (Golub, Heath & Wahba 1979).

The smoothness prior's weight alpha per channel and prior variant, as the minimiser of
``GCV(alpha) = rho / (1 - tr(H)/M)^2`` of the unconstrained Tikhonov problem, scanned
on a log grid (:data:`GCV_ALPHAS`) and refined by a parabola through the best three.
Measured to over-fit clean images (``docs/recovery.md``), so it is opt-in (``alpha="gcv"``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np

from mi_bivariate.errors import InputError
from mi_bivariate.solve.common import penalty_weight
from mi_bivariate.solve.data_term import DataTerm
from mi_bivariate.solve.lapack import cho_factor, cho_solve

#: The alphas GCV scans (log-spaced; refined by a parabola through the best three).
GCV_ALPHAS = tuple(10.0 ** np.arange(-8.0, 2.01, 1.0))
#: Rademacher probes of the Hutchinson trace estimate (seeded: deterministic).
GCV_PROBES = 16


@dataclass
class GCVCurve:
    """Generalised cross-validation of one channel and prior (unconstrained Tikhonov)."""
    alphas: np.ndarray      #: (A,) scanned alphas
    scores: np.ndarray      #: (A,) GCV(alpha) = rho / (1 - tr(H)/M)^2, rho the mean squared weighted residual
    dof: np.ndarray         #: (A,) tr(H): effective number of parameters
    alpha: float            #: the minimiser (log-parabolic refinement)
    score: float            #: GCV at the refined alpha (interpolated)


def gcv_curve(data: DataTerm, penalty: np.ndarray, k: int, alphas: Sequence[float] = GCV_ALPHAS,
              probes: int = GCV_PROBES, seed: int = 0, extra: Optional[Tuple[np.ndarray, np.ndarray]] = None
              ) -> GCVCurve:
    """GCV(alpha) of channel ``k`` (Golub, Heath & Wahba 1979) with a Hutchinson trace.

    ``H = A X^-1 A^T`` with ``X = gram + lambda P``; ``tr(H) = tr(X^-1 gram)``
    ``= N - lambda tr(X^-1 P)``, the latter estimated with seeded Rademacher
    probes. The residual is exact: ``rho = yy - 2 f^T rhs + f^T gram f``. The
    positivity constraint is ignored here (it only lowers the effective degrees
    of freedom); the chosen alpha is then used in the constrained solve.
    ``extra = (precision, shift)``, both ``(N,)``: a fixed diagonal Gaussian term
    (the basis prior) added to ``X`` and to the right-hand side.
    """
    n = data.n_nodes
    m = data.n_rows
    rng = np.random.default_rng(seed)
    z = rng.choice([-1.0, 1.0], size=(n, probes))
    pz = penalty @ z
    g, b = data.gram[k], data.rhs[k]
    fixed, shift = (np.zeros(n), np.zeros(n)) if extra is None else extra
    scores, dofs = [], []
    for alpha in alphas:
        lam = penalty_weight(alpha, data.n_nodes, data.level[k])
        x = g + lam * penalty
        x[np.diag_indices(n)] += fixed
        try:
            factor = cho_factor(x)
        except np.linalg.LinAlgError:  # X not numerically positive definite at this alpha: not a candidate
            dofs.append(np.nan)
            scores.append(np.inf)
            continue
        f = cho_solve(factor, b + shift)
        rho = max(data.yy[k] - 2.0 * f @ b + f @ g @ f, 0.0)
        # tr(X^-1 gram) = N - tr(X^-1 (lam P + diag(fixed)))
        other = lam * pz + fixed[:, None] * z
        trace = n - float(np.mean(np.sum(z * cho_solve(factor, other), axis=0)))
        dof = float(np.clip(trace, 0.0, min(n, m - 1)))
        dofs.append(dof)
        scores.append(rho / (1.0 - dof / m) ** 2)
    alphas = np.asarray(alphas, dtype=np.float64)
    scores = np.asarray(scores)
    if not np.any(np.isfinite(scores)):
        raise InputError("prior", "the system cannot be factorised at any alpha GCV scans (the smoothness "
                         "prior is too ill-conditioned)", "give alpha as a number or 'discrepancy'")
    best, score = _minimum(alphas, scores)
    return GCVCurve(alphas, scores, np.asarray(dofs), best, score)


def _minimum(alphas: np.ndarray, scores: np.ndarray) -> Tuple[float, float]:
    """``(alpha, score)`` at the smallest score, refined by a parabola through log GCV at the best three
    when they are finite and positive (an exact fit scores 0, a failed factorisation infinity)."""
    i = int(np.argmin(scores))
    best, score = float(alphas[i]), float(scores[i])
    near = scores[i - 1:i + 2]
    if 0 < i < len(alphas) - 1 and np.all(np.isfinite(near)) and np.all(near > 0):
        x = np.log10(alphas[i - 1:i + 2])
        c2, c1, c0 = np.polyfit(x, np.log(near), 2)
        if c2 > 0:
            x_min = float(np.clip(-c1 / (2 * c2), x[0], x[2]))
            best, score = 10.0 ** x_min, float(np.exp(np.polyval([c2, c1, c0], x_min)))
    return best, score

