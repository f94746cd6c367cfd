"""Non-negative least squares on the normal equations: block principal pivoting.

``min 1/2 x^T G x - b^T x`` s.t. ``x >= 0`` (i.e. ``min ||A x - a||^2`` with
``G = A^T A``, ``b = A^T a``), by Kim & Park's block principal pivoting with
Murty's single-exchange fallback. Every answer's KKT conditions are verified;
if they fail, the problem is re-solved with ``scipy.optimize.nnls`` on an
eigen-reduced ``N x N`` system and the result says so.

From a start with every variable passive (the solve's usual start: the Lambertian
level, or the basis prior's mean where it is positive everywhere; a zero entry sends
the solve to direct factorisations), ``G`` is factorised once and every
later passive-set solve works on that one factor (:class:`_SchurSolver`): with ``A``
the active set, ``x = z + G^-1 E mu``, ``z = G^-1 b``, ``(G^-1)_AA mu = -z_A``, where
``E`` selects ``A`` and ``mu`` is the gradient on ``A``. A passive-set solve then costs
the columns of ``G^-1`` for variables new to ``A`` (two triangular solves each) and an
``|A| x |A|`` factorisation, instead of a factorisation of ``G_FF``. That factor of
``G`` is returned with the answer, and the confidence
(:mod:`mi_bivariate.solve.confidence`) reuses it instead of factorising ``G`` again.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np
import scipy.linalg as sla

from mi_bivariate.solve.common import KKT_TOLERANCE, cholesky
from mi_bivariate.solve.lapack import cho_factor, cho_solve

# Sign threshold (relative) for moving a variable between sets: below it, a negative x
# or gradient is round-off, and exchanging it would only make the pivoting cycle.
_EXCHANGE_TOLERANCE = 1e-12
# Block exchanges allowed without progress before Murty's single exchange (Kim & Park).
_BPP_BACKUP = 3
# Passive-set solves before handing over to the fallback. Block pivoting typically needs
# 1-10 on the lighting matrices seen so far; Murty's rule alone could need up to ~N.
_MAX_ITER = 100


@dataclass
class NNLSResult:
    """Solution of ``min 1/2 x^T G x - b^T x, x >= 0``."""
    x: np.ndarray            #: (N,) float64, >= 0
    iterations: int          #: passive-set linear solves
    kkt_violation: float     #: relative, see :func:`kkt_violation`
    method: str              #: "bpp" or "bpp+nnls-fallback"
    #: ``cho_factor`` of the whole ``G`` when the solve had it (the one-factor route, or a
    #: final passive set of every variable), else ``None``
    factor: Optional[Tuple[np.ndarray, bool]] = None
    #: ``log det G`` when some passive-set solve factorised all of ``G`` (the usual first
    #: one, from a positive start), else ``None``
    log_det: Optional[float] = None


def kkt_violation(G: np.ndarray, b: np.ndarray, x: np.ndarray, abs_g: Optional[np.ndarray] = None) -> float:
    """Relative KKT violation of ``x`` for ``min 1/2 x^T G x - b^T x, x >= 0``.

    The natural residual ``max_i |min(x_i / x_scale, g_i / g_scale)|`` with the gradient
    ``g = G x - b``: zero exactly at the solution; it measures primal infeasibility
    (x_i < 0), dual infeasibility (g_i < 0) and complementarity (both > 0) at once.
    ``x_scale = max |x|`` and ``g_scale = max |b| + max (|G| |x|)``, the size of the terms
    that cancel in g, so round-off gives ~1e-15 whatever the conditioning. ``abs_g``:
    ``|G|`` if the caller has it.
    """
    x = np.asarray(x, dtype=np.float64)
    abs_g = np.abs(G) if abs_g is None else abs_g
    g = G @ x - b
    x_scale = float(np.abs(x).max(initial=0.0)) or 1.0
    g_scale = float(np.abs(b).max(initial=0.0) + (abs_g @ np.abs(x)).max(initial=0.0)) or 1.0
    return float(np.abs(np.minimum(x / x_scale, g / g_scale)).max(initial=0.0))


def _passive_solve(G: np.ndarray, b: np.ndarray, passive: np.ndarray):
    """x with ``G_FF x_F = b_F``, 0 elsewhere, the gradient ``y = G x - b`` (0 on F), and
    the Cholesky factor of ``G_FF`` (``None`` if it was singular)."""
    x = np.zeros_like(b)
    idx = np.flatnonzero(passive)
    factor = None
    if idx.size:
        g_ff = G if idx.size == b.size else G[np.ix_(idx, idx)]
        try:
            factor = cho_factor(g_ff)
            x_f = cho_solve(factor, b[idx])
            if not np.all(np.isfinite(x_f)):
                raise np.linalg.LinAlgError
        except np.linalg.LinAlgError:
            # Singular sub-problem (alpha = 0 with a rank-deficient L): minimum-norm solution.
            factor = None
            x_f = sla.lstsq(g_ff, b[idx], check_finite=False)[0]
        x[idx] = x_f
    y = G @ x - b
    y[idx] = 0.0
    return x, y, factor


class _SchurSolver:
    """Passive-set solves of ``min 1/2 x^T G x - b^T x`` s.t. ``x_A = 0`` from one factor of ``G``.

    Lagrange: ``G x - b = E mu``, ``E^T x = 0`` give ``x = z + C mu`` with ``z = G^-1 b``,
    ``C = G^-1 E`` (``(N, |A|)``) and ``C_A mu = -z_A``; ``mu`` is then the gradient
    ``G x - b`` on ``A`` (0 on the passive set). Columns of ``G^-1`` are computed once,
    when their variable first turns active (one ``cho_solve`` for all of them).
    """

    def __init__(self, b: np.ndarray, factor: Tuple[np.ndarray, bool]):
        self.factor = factor
        self.z = cho_solve(factor, b)
        self.slot = np.full(b.size, -1)
        self.columns = np.empty((b.size, 0))

    def _columns(self, active: np.ndarray) -> np.ndarray:
        new = active[self.slot[active] < 0]
        if new.size:
            unit = np.zeros((self.z.size, new.size))
            unit[new, np.arange(new.size)] = 1.0
            self.slot[new] = self.columns.shape[1] + np.arange(new.size)
            self.columns = np.hstack([self.columns, cho_solve(self.factor, unit)])
        return self.columns[:, self.slot[active]]

    def __call__(self, passive: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """``x`` and the gradient ``y = G x - b`` (0 on the passive set)."""
        x, y = self.z.copy(), np.zeros_like(self.z)
        active = np.flatnonzero(~passive)
        if active.size:
            c = self._columns(active)
            c_aa = c[active]
            mu = cho_solve(cho_factor(0.5 * (c_aa + c_aa.T), overwrite=True), -self.z[active])
            if not np.all(np.isfinite(mu)):
                raise np.linalg.LinAlgError("singular active-set system")
            x += c @ mu
            x[active] = 0.0
            y[active] = mu
        return x, y


def _factors(factor: Tuple[np.ndarray, bool], G: np.ndarray) -> bool:
    """Whether ``factor`` (``(c, lower)``) is, to round-off, a Cholesky factor of ``G``: ``diag(L L^T)
    = diag(G)`` (``O(N^2)``; a factor of another system fails it)."""
    c, lower = factor
    if c.shape != G.shape:
        return False
    tri = np.tril(c) if lower else np.triu(c)
    norms = np.einsum("ij,ij->i", tri, tri) if lower else np.einsum("ij,ij->j", tri, tri)
    return bool(np.allclose(norms, np.diag(G), rtol=1e-10, atol=0.0))


def _full_log_det(factor: Optional[Tuple[np.ndarray, bool]], passive: np.ndarray) -> Optional[float]:
    """``log det G`` from the passive-set factor when the passive set is every variable."""
    if factor is None or not bool(np.all(passive)):
        return None
    return 2.0 * float(np.sum(np.log(np.diag(factor[0]))))


def _nnls_fallback(G: np.ndarray, b: np.ndarray) -> np.ndarray:
    """scipy.optimize.nnls on ``||R x - d||`` with ``R^T R = G``, ``R^T d = b``."""
    # Imported here: the fallback almost never runs and scipy.optimize costs ~0.2 s to import.
    from scipy.optimize import nnls

    w, v = np.linalg.eigh(G)
    keep = w > max(w.max(initial=0.0), 0.0) * G.shape[0] * np.finfo(np.float64).eps
    root = np.sqrt(w[keep])
    r = root[:, None] * v[:, keep].T
    d = (v[:, keep].T @ b) / root
    x, _ = nnls(r, d, maxiter=50 * G.shape[0])
    return np.maximum(x, 0.0)


def nnls_gram(G: np.ndarray, b: np.ndarray, passive: Optional[np.ndarray] = None, *,
              max_iter: Optional[int] = None, tol: float = KKT_TOLERANCE,
              factor: Optional[Tuple[np.ndarray, bool]] = None) -> NNLSResult:
    """Non-negative least squares from its normal equations by block principal pivoting.

    Solves ``min 1/2 x^T G x - b^T x`` s.t. ``x >= 0`` (i.e. ``min ||A x - a||^2`` with
    ``G = A^T A``, ``b = A^T a``). Kim & Park, "Fast nonnegative matrix factorization: an
    active-set-like method and comparisons", SIAM J. Sci. Comput. 33 (2011), Alg. 1:
    exchange every infeasible variable between the passive and active sets at once,
    and after ``_BPP_BACKUP`` exchanges without fewer infeasibles only the one with the
    largest index (Murty's rule, which terminates).

    Args:
        G: ``(N, N)`` float64, symmetric positive (semi)definite.
        b: ``(N,)`` float64.
        passive: ``(N,)`` bool initial passive set (the variables free to be > 0);
            default empty (x = 0).
        max_iter: passive-set solves before giving up on pivoting (default 100).
        tol: accepted :func:`kkt_violation`; beyond it the fallback solver runs.
        factor: the Cholesky factor of ``G`` (``(c, lower)``) if the caller has it: the start with
            every variable passive uses it instead of factorising ``G`` again.
    """
    n = b.size
    passive = np.zeros(n, dtype=bool) if passive is None else np.array(passive, dtype=bool)
    max_iter = _MAX_ITER if max_iter is None else int(max_iter)
    # A zero diagonal entry is a variable the objective ignores (an st node no pixel sees,
    # without a prior): G's row and column and b's entry are 0 there. Fix it at 0 rather
    # than hand singular sub-problems to the pivoting.
    seen = np.diag(G) > 0
    if not np.all(seen):
        sub = nnls_gram(G[np.ix_(seen, seen)], b[seen], passive[seen], max_iter=max_iter, tol=tol)
        x = np.zeros(n)
        x[seen] = sub.x
        return NNLSResult(x, sub.iterations, kkt_violation(G, b, x), sub.method)
    abs_g = np.abs(G)
    b_scale = np.abs(b).max(initial=0.0)

    schur = None
    # The factor of all of G (the caller's, checked to be G's: its rows' norms are G's diagonal; or
    # computed), kept for the result.
    if factor is not None and not _factors(factor, G):
        factor = None
    whole = (factor if factor is not None else cholesky(G)) if np.all(passive) else None
    if whole is not None:
        schur = _SchurSolver(b, whole)
        x, y = schur(passive)
        factor = whole
    else:
        x, y, factor = _passive_solve(G, b, passive)
    log_det = _full_log_det(factor, passive)
    iterations, best, backup = 1, n + 1, _BPP_BACKUP
    while iterations < max_iter:
        x_tol = _EXCHANGE_TOLERANCE * np.abs(x).max(initial=0.0)
        y_tol = _EXCHANGE_TOLERANCE * (b_scale + (abs_g @ np.abs(x)).max(initial=0.0))
        infeasible = (passive & (x < -x_tol)) | (~passive & (y < -y_tol))
        count = int(infeasible.sum())
        if count == 0:
            break
        if count < best:
            best, backup = count, _BPP_BACKUP
            passive ^= infeasible
        elif backup > 0:
            backup -= 1
            passive ^= infeasible
        else:
            last = np.flatnonzero(infeasible)[-1]
            passive[last] = ~passive[last]
        if schur is not None:
            try:
                x, y = schur(passive)
            except np.linalg.LinAlgError:
                schur = None  # (G^-1)_AA not numerically SPD: factorise G_FF from here on
        if schur is None:
            x, y, factor = _passive_solve(G, b, passive)
            log_det = _full_log_det(factor, passive) if log_det is None else log_det
        iterations += 1

    x = np.maximum(x, 0.0)
    violation = kkt_violation(G, b, x, abs_g)
    if schur is not None and not violation <= tol and not np.all(passive):
        # Round-off of the one-factor route (cond(G) rather than cond(G_FF)): one direct solve
        # on the final passive set.
        x_f, _, _ = _passive_solve(G, b, passive)
        x = np.maximum(x_f, 0.0)
        violation = kkt_violation(G, b, x, abs_g)
    method = "bpp"
    if not violation <= tol:
        x = _nnls_fallback(G, b)
        violation = kkt_violation(G, b, x, abs_g)
        method = "bpp+nnls-fallback"
    if method != "bpp":
        kept = None
    elif whole is not None:
        kept = whole
    else:
        kept = factor if bool(np.all(passive)) else None
    return NNLSResult(x, iterations, violation, method, kept, log_det)
