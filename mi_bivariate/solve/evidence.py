"""Choosing the prior variant: the evidence (marginal likelihood) of the image under each weight pair.

Every weight pair of the smoothness prior (paper Sect. 4: ``"diffuse"`` and ``"gloss"``) is a
Gaussian prior on the table, and each is solved. The paper keeps the pair with the lower data
residual. That rule ignores what the fit cost: a pair that lets the table bend more always fits
at least as well, and the residual cannot tell a better prior from a looser one. The evidence
of the image under each prior weighs both (MacKay 1992, "Bayesian interpolation"); the pair
with the higher evidence is kept.

For one channel, with the solve's normalisation (:mod:`mi_bivariate.solve`), ``y = I / (sigma
sqrt(M))``, ``A = L / (sigma sqrt(M))``, ``G = A^T A``, the prior's weight ``lambda`` and precision
``P = R^T R``: the image is modelled as ``y ~ N(A f, 1 / M)`` (each row's ``sigma`` is its noise,
as the data term and the discrepancy principle take it) and the table as
``f ~ N(0, (lambda P)^+ / M)``. Integrating out ``f``:

    log p(y | pair) = -(M / 2) Phi - 1/2 log det(G + lambda P) + 1/2 log pdet(lambda P) + c,

    Phi = min_f ||y - A f||^2 + lambda f^T P f,

where ``c`` depends only on ``M``, ``N`` and ``rank P``. Both pairs are weighted first
differences: the constant table is unpenalised, and the formula is the limit of the proper
priors ``lambda P + eps J / N`` (``eps -> 0``, ``J`` all ones), whose ``eps`` terms the pairs
share. With the non-negativity constraint, ``Phi`` is the constrained minimum (the Laplace
approximation at the non-negative MAP estimate). A diagonal Gaussian table prior (the basis
prior's second stage) joins ``lambda P`` in the prior precision, which is then of full rank.

Chosen on 42 *training* materials, never on a scored one (``benchmarks/pair_rule.py``,
``docs/recovery.md`` section 4b). Against the residual rule, one image under grace relit at a
median 1.14x the relight floor instead of 1.22x (geometric mean 0.99 against 1.04): better on 7
materials, worse on 1, the same on 34. The gains are glossy materials where the residual kept
"diffuse" for one channel. The rule was within 0.03 of the best choice in hindsight. Taking the
noise scale from the residual changed nothing; integrating it out weighed the fit less and did
worse (1.20).
"""

from __future__ import annotations

from typing import Optional, Tuple

import numpy as np
import scipy.linalg
import scipy.sparse
from scipy.sparse.csgraph import connected_components

from mi_bivariate.errors import InputError
from mi_bivariate.solve.common import banded_cholesky, bandwidth, cholesky

#: How the prior variant (weight pair) is chosen per channel: ``"evidence"`` (the default,
#: :func:`log_evidence`) or ``"residual"`` (the paper's: the lower data residual).
PAIR_RULES = ("evidence", "residual")
DEFAULT_PAIR_RULE = "evidence"


def check_pair_rule(pair_rule: object) -> str:
    """``pair_rule`` if it is one of :data:`PAIR_RULES`, else :class:`InputError` naming ``pair_rule``."""
    if not isinstance(pair_rule, str) or pair_rule not in PAIR_RULES:
        raise InputError("pair_rule", f"unknown rule {pair_rule!r}", f"use one of {', '.join(PAIR_RULES)}")
    return pair_rule


def log_det_spd(x: np.ndarray) -> float:
    """``log det X`` of a symmetric positive definite ``(N, N)`` matrix (Cholesky; slogdet if not SPD)."""
    factor = cholesky(x)
    if factor is not None:
        return 2.0 * float(np.sum(np.log(np.diag(factor[0]))))
    sign, value = np.linalg.slogdet(x)
    return float(value) if sign > 0 else -np.inf


def log_det_banded(x: np.ndarray, band: Optional[int] = None) -> float:
    """``log det X`` of a banded SPD ``(N, N)`` matrix (LAPACK ``pbtrf``, ``O(N b^2)``; dense if that fails).

    ``band``: the bandwidth if the caller knows it (finding it scans all ``N^2`` entries).
    """
    b = max(bandwidth(x) if band is None else int(band), 1)
    u = banded_cholesky(x, b)
    return 2.0 * float(np.sum(np.log(u[b]))) if u is not None else log_det_spd(x)


def penalty_log_pdet(penalty: np.ndarray, band: Optional[int] = None) -> Tuple[float, int]:
    """``(log pdet P, rank P)`` of a prior precision ``P`` ``(N, N)`` (symmetric, PSD); ``band``: its
    bandwidth if the caller knows it.

    A weighted graph Laplacian (rows summing to 0, as the smoothness prior's ``R^T R`` on a
    connected grid) has the constant table as its only null vector; then ``pdet P = N det
    P'``, ``P'`` being ``P`` without its first row and column (the matrix-tree theorem), a
    banded matrix factorised in ``O(N b^2)``. Anything else (a graph in several pieces included,
    whose ``P'`` is singular but may factorise by round-off): the eigenvalues above ``N eps max``.
    """
    p = np.asarray(penalty, np.float64)
    n = p.shape[0]
    scale = float(np.abs(p).max(initial=0.0))
    if scale == 0.0:
        return 0.0, 0
    if n > 1 and float(np.abs(p.sum(axis=1)).max()) <= 1e-10 * scale * n and _connected(p, band):
        sub = p[1:, 1:]
        log_det = log_det_banded(sub, band)
        if np.isfinite(log_det):
            return float(np.log(n)) + log_det, n - 1
    w = np.linalg.eigvalsh(p)
    keep = w > n * np.finfo(np.float64).eps * w.max()
    return float(np.sum(np.log(w[keep]))), int(keep.sum())


def _connected(p: np.ndarray, band: Optional[int] = None) -> bool:
    """Whether the graph of the symmetric ``(N, N)`` matrix's non-zero entries joins every node (one
    piece); ``band``: its bandwidth if the caller knows it (the edges are then read in ``O(N b)``)."""
    n = p.shape[0]
    offsets = range(1, (bandwidth(p) if band is None else int(band)) + 1)
    starts = [np.flatnonzero(np.diagonal(p, d)) for d in offsets]
    rows = np.concatenate([np.zeros(0, np.int64)] + starts)
    cols = rows + np.repeat(np.array(offsets, np.int64), [len(s) for s in starts])
    graph = scipy.sparse.coo_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n))
    return connected_components(graph, directed=False, return_labels=False) == 1


def log_evidence(objective: float, system_log_det: float, prior_log_pdet: float, n_rows: int) -> float:
    """``log p(y | prior)`` up to a constant shared by priors of equal rank (see the module's notes).

    Args:
        objective: ``Phi``, the minimum of ``||y - A f||^2 + f^T Q f`` (plus the table prior's
            term; dimensionless, the data term plus the prior terms as :mod:`mi_bivariate.solve`
            normalises them).
        system_log_det: ``log det(G + Q)``, the normal equations' matrix.
        prior_log_pdet: ``log pdet Q``, the prior precision.
        n_rows: ``M``.
    """
    return -0.5 * int(n_rows) * float(objective) - 0.5 * system_log_det + 0.5 * prior_log_pdet


def channel_log_evidence(objective: float, n_rows: int, system_log_det: float, lam: float, penalty: np.ndarray,
                         penalty_pdet: Tuple[float, int], precision: Optional[np.ndarray] = None,
                         mean: Optional[np.ndarray] = None) -> float:
    """:func:`log_evidence` of one channel of the solve.

    Args:
        objective: ``Phi`` at the solution.
        n_rows: ``M``.
        system_log_det: ``log det`` of the normal equations' ``(N, N)`` matrix
            ``G + lambda P [+ diag(precision)]``.
        lam: ``lambda`` (:func:`~mi_bivariate.solve.common.penalty_weight`).
        penalty: ``(N, N)`` ``P``.
        penalty_pdet: ``(log pdet P, rank P)`` (:func:`penalty_log_pdet`).
        precision: ``(N,)`` the table prior's diagonal precision, if any: the prior precision
            is then ``lambda P + diag(precision)``, of full rank (banded: ``O(N b^2)``).
        mean: ``(N,)`` the table prior's mean (default 0). ``Phi`` holds ``(f - mean)^T D (f - mean)``
            with ``D = diag(precision)``; the prior of the evidence is the Gaussian of precision
            ``Q = lambda P + D`` about ``m0 = Q^-1 D mean``, whose exponent is ``Phi`` less the constant
            ``mean^T D mean - m0^T Q m0``. That constant depends on the pair (through ``P``), so it is
            taken out (one dense solve).
    """
    if precision is not None:
        q = lam * np.asarray(penalty, np.float64)
        q[np.diag_indices_from(q)] += precision
        if mean is not None and np.any(mean != 0.0):
            b = np.asarray(precision, np.float64) * np.asarray(mean, np.float64)
            m0 = scipy.linalg.solve(q, b, assume_a="pos")
            objective = objective - (float(b @ mean) - float(b @ m0))
        return log_evidence(objective, system_log_det, log_det_banded(q), n_rows)
    log_pdet, rank = penalty_pdet
    if lam <= 0.0 or rank == 0:  # a flat prior: nothing to weigh but the fit
        return log_evidence(objective, system_log_det, 0.0, n_rows)
    return log_evidence(objective, system_log_det, rank * float(np.log(lam)) + log_pdet, n_rows)
