"""Shared pieces of the solve: constants, input checks, and symmetric positive definite algebra.

The linear algebra here is what every algorithm of the package needs from one
Cholesky factorisation ``X = U^T U`` of an ``N x N`` float64 system:
:func:`cholesky` (``None`` when ``X`` is not numerically positive definite),
:func:`inverse_from_cholesky` (LAPACK ``potri``: ``X^-1`` from ``U`` in 2/3 N^3
flops, a third of solving against the identity) and :func:`banded_inverse_diagonal`
(the diagonal of the inverse of a banded matrix in ``O(N b^2)``, Takahashi's
recurrence by blocks, for the smoothness prior's sparse normal matrix).
"""

from __future__ import annotations

from typing import Optional, Tuple, Union

import numpy as np
from scipy.linalg import lapack

from mi_bivariate.errors import InputError
from mi_bivariate.prior import Prior
from mi_bivariate.solve import lapack as gil_free

#: The learnt weight alpha of the normalised smoothness term (see :mod:`mi_bivariate.solve`):
#: the upper bound of the discrepancy principle's alpha, and the fixed weight where residuals of
#: several configurations are compared (yaw alignment). Chosen on 8 of the 50 *training*
#: MERL-NBRDF materials (never on a scored one) with the default model-error form and the
#: basis prior, by the median over materials of the relight error under three novel probes
#: divided by the exact reduction's
#: (benchmarks/ablation.py, docs/recovery.md): 1.27 at 1e-2 (GCV per recovery: 1.91,
#: it over-fits the model error, which is correlated between neighbouring pixels).
DEFAULT_ALPHA = 1e-2
#: How alpha is chosen when none is given: the discrepancy principle (:mod:`~mi_bivariate.solve.discrepancy`).
DEFAULT_ALPHA_RULE = "discrepancy"
#: The rules that choose alpha per recovery from the data.
ALPHA_RULES = ("discrepancy", "gcv")
#: Largest accepted KKT violation (relative natural residual, see :func:`~mi_bivariate.solve.kkt_violation`).
KKT_TOLERANCE = 1e-9


def validate_problem(L: np.ndarray, I: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Check ``L (M, N, 3)`` and ``I (M, 3)``: shapes, dtypes, finiteness, ``M, N > 0``."""
    L = np.asarray(L)
    I = np.asarray(I)
    if L.ndim != 3 or L.shape[2] != 3:
        raise InputError("lighting matrix L", f"expected shape (M, N, 3), got {L.shape}")
    if I.ndim != 2 or I.shape[1] != 3:
        raise InputError("observations I", f"expected shape (M, 3), got {I.shape}")
    if L.shape[0] != I.shape[0]:
        raise InputError("lighting matrix L", f"has {L.shape[0]} rows but there are {I.shape[0]} observations")
    if L.shape[0] == 0:
        raise InputError("observations I", "no observations (M = 0)",
                         "check the mask, the view-angle limit and saturation")
    if L.shape[1] == 0:
        raise InputError("lighting matrix L", "has no columns (N = 0)")
    for name, arr in (("lighting matrix L", L), ("observations I", I)):
        if not np.issubdtype(arr.dtype, np.floating) and not np.issubdtype(arr.dtype, np.integer):
            raise InputError(name, f"has non-numeric dtype {arr.dtype}")
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        if bad:
            raise InputError(name, f"has {bad} NaN or infinite entries")
    return L, I


def grid_shape(n_nodes: int, prior: Prior, n_t: Optional[int], n_s: Optional[int]) -> Tuple[int, int]:
    """The st grid ``(n_t, n_s)`` of ``n_nodes`` columns: given, the prior's, or square."""
    if n_t is None and n_s is None:
        if prior.n_t * prior.n_s == n_nodes:
            return prior.n_t, prior.n_s
        root = int(round(np.sqrt(n_nodes)))
        if root * root == n_nodes:
            return root, root
        raise InputError("lighting matrix L", f"{n_nodes} columns is not a square grid",
                         "pass n_t and n_s")
    if n_t is None or n_s is None or n_t * n_s != n_nodes:
        raise InputError("lighting matrix L", f"{n_nodes} columns do not match the grid {n_t} x {n_s}")
    return int(n_t), int(n_s)


#: Given alphas other than 0 (no smoothness term) must lie in this range: beyond it the normal
#: equations lose every digit of the data term (above) or of the prior (below) in float64.
ALPHA_RANGE = (1e-12, 1e6)


def check_alpha(alpha) -> Union[str, np.ndarray]:
    """A rule of :data:`ALPHA_RULES` (``None``: :data:`DEFAULT_ALPHA_RULE`), or given alphas as ``(3,) float64``.

    A given alpha is one number (every channel) or three (per channel): 0 or within :data:`ALPHA_RANGE`.
    """
    if alpha is None:
        alpha = DEFAULT_ALPHA_RULE
    if isinstance(alpha, str):
        if alpha in ALPHA_RULES:
            return alpha
        try:
            alpha = float(alpha)
        except ValueError:
            raise InputError("alpha", f"must be a number or one of {', '.join(ALPHA_RULES)}, got {alpha!r}") from None
    try:
        values = np.broadcast_to(np.asarray(alpha, np.float64), (3,)).copy()
    except (TypeError, ValueError):
        raise InputError("alpha", f"must be a number (or 3) or one of {', '.join(ALPHA_RULES)}, "
                         f"got {alpha!r}") from None
    if not np.all(np.isfinite(values)) or np.any(values < 0):
        raise InputError("alpha", f"must be finite and >= 0, got {alpha}", "1e-2 is the learnt default")
    lo, hi = ALPHA_RANGE
    if np.any((values != 0) & ((values < lo) | (values > hi))):
        raise InputError("alpha", f"must be 0 or between {lo:g} and {hi:g} (alpha is dimensionless: 1e-2 is the "
                                  f"learnt default), got {alpha}")
    return values


def penalty_weight(alpha: float, n_nodes: int, level: float) -> float:
    """lambda = alpha / (N level^2): the prior term's weight in the normal equations."""
    level = level if level > 0 else 1.0
    return alpha / (n_nodes * level * level)


def cholesky(x: np.ndarray) -> Optional[Tuple[np.ndarray, bool]]:
    """The Cholesky factor ``(c, lower)`` (as ``scipy.linalg.cho_factor``, computed without the GIL:
    :mod:`~mi_bivariate.solve.lapack`) of a float64 SPD matrix, or ``None`` if it is not
    (numerically) SPD."""
    try:
        factor = gil_free.cho_factor(x)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(np.diag(factor[0]))):
        return None
    return factor


def inverse_from_cholesky(factor: Tuple[np.ndarray, bool], full: bool = True) -> np.ndarray:
    """``X^-1`` from ``cho_factor(X)``, by LAPACK ``potri``.

    ``full=False`` returns only the factor's triangle of the inverse (zeros elsewhere).
    """
    inv = gil_free.potri(factor)
    # potri fills one triangle; the other holds the factor's leftovers.
    tri = np.tril(inv) if factor[1] else np.triu(inv)
    if not full:
        return tri
    return tri + tri.T - np.diag(np.diag(tri))


def sparse_entries(x: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(rows, cols, values)`` of the non-zero entries of a dense ``(N, N)`` matrix.

    The priors' matrices (``R^T R`` of the smoothness prior, the table prior's diagonal)
    have a few entries per row: adding them to a Gram matrix, or evaluating ``f^T P f``,
    by their entries costs ``O(nnz)`` instead of ``O(N^2)``.
    """
    rows, cols = np.nonzero(x)
    return rows, cols, x[rows, cols]


def add_entries(x: np.ndarray, entries: Tuple[np.ndarray, np.ndarray, np.ndarray],
                weight: float = 1.0) -> np.ndarray:
    """``x += weight * P`` in place for ``P`` given by its entries (repeated entries add up);
    returns ``x``."""
    rows, cols, values = entries
    np.add.at(x, (rows, cols), weight * values)
    return x


def quadratic_form(entries: Tuple[np.ndarray, np.ndarray, np.ndarray], f: np.ndarray) -> float:
    """``f^T P f`` for ``P`` given by :func:`sparse_entries`."""
    rows, cols, values = entries
    return float(np.dot(values, f[rows] * f[cols]))


#: Most diagonals of ``X^-1`` that :func:`inverse_diagonals` reads from the inverse factor
#: (``O(N^2)`` each); a prior with entries on more is read from ``potri``'s whole inverse.
MAX_INVERSE_DIAGONALS = 16


def _inverse_at_offsets(inv_factor: np.ndarray, lower: bool, offsets: np.ndarray) -> dict:
    """``{d: z_d}`` with ``z_d[i] = (X^-1)_{i, i + d}`` (``(N - d,)``) for each offset ``d >= 0``, from
    ``W``, the inverse Cholesky factor in ``inv_factor``'s ``lower`` (or upper) triangle
    (:func:`~mi_bivariate.solve.lapack.trtri`): ``X^-1 = W^T W`` (lower), so an entry is the dot
    product of two columns of ``W``; ``W W^T`` (upper), of two rows. ``O(N^2)`` per offset.
    ``inv_factor``'s other triangle is set to zero (in place: no second ``N x N`` array)."""
    n = inv_factor.shape[0]
    w = inv_factor
    keep = np.tril if lower else np.triu
    for start in range(0, n, 64):  # the other triangle's leftovers zeroed in place, 64 rows at a time
        w[start:start + 64] = keep(w[start:start + 64], start)
    pattern = "ki,ki->i" if lower else "ik,ik->i"
    return {int(d): (np.einsum(pattern, w[:, : n - d], w[:, d:]) if lower else
                     np.einsum(pattern, w[: n - d], w[d:])) for d in offsets}


def inverse_diagonals(x: np.ndarray, gram: np.ndarray,
                      factor: Optional[Tuple[np.ndarray, bool]] = None,
                      prior: Optional[Tuple[np.ndarray, np.ndarray, np.ndarray]] = None,
                      overwrite_factor: bool = False) -> Tuple[np.ndarray, np.ndarray]:
    """``diag(X^-1)`` and ``diag(X^-1 gram)`` (gram symmetric) from one factorisation of ``X``.

    ``prior``: the entries (:func:`sparse_entries`) of ``Q = X - gram`` (symmetric and
    sparse: the priors' part of the system). Then ``diag(X^-1 gram) = 1 - diag(X^-1 Q)``
    reads ``X^-1`` only where ``Q`` is non-zero: on the few diagonals ``|i - j| = d`` that
    hold ``Q``'s entries (the smoothness prior's: ``d`` in 0, 1, ``n_s``), each from the
    inverse factor ``W = L^-1`` (LAPACK ``trtri``, half of ``potri``'s flops) in ``O(N^2)``.
    Without it: with ``T`` one triangle of ``X^-1`` (``potri``) and ``P = T * gram``
    elementwise, ``diag(X^-1 gram)_i = sum_j P_ij + sum_j P_ji - P_ii`` (``O(N^2)``). Falls
    back to the pseudo-inverse when ``X`` is singular. ``overwrite_factor``: the inverse takes
    the given factor's memory (one ``N x N`` array less alive; the factor is lost).
    """
    own = factor is None
    factor = cholesky(x) if factor is None else factor
    offsets = None
    if prior is not None:
        lo, hi = np.minimum(prior[0], prior[1]), np.maximum(prior[0], prior[1])
        offsets = np.union1d(hi - lo, [0])
    # A few diagonals from the inverse factor; a prior spread over many (not the smoothness prior's) reads potri's X^-1.
    by_diagonals = offsets is not None and len(offsets) <= MAX_INVERSE_DIAGONALS
    inv = None
    if factor is not None:
        try:
            routine = gil_free.trtri if by_diagonals else gil_free.potri
            inv = routine(factor, overwrite=own or overwrite_factor)
        except np.linalg.LinAlgError:
            inv = None
    if inv is None:
        pinv = np.linalg.pinv(x)
        return np.diag(pinv).copy(), np.einsum("ij,ij->i", pinv, gram)
    lower = factor[1]
    if prior is not None:
        rows, _, values = prior
        if by_diagonals:
            z = _inverse_at_offsets(inv, lower, offsets)
            offset = hi - lo
            inside = np.empty(len(values))
            for d in offsets:  # (X^-1)_ij of every entry, from its diagonal
                sel = offset == d
                inside[sel] = z[int(d)][lo[sel]]
            variance = z[0]
        else:
            inside = inv[hi, lo] if lower else inv[lo, hi]  # (X^-1)_ij from the valid triangle
            variance = np.diag(inv).copy()
        x_inv_q = np.bincount(rows, weights=inside * values, minlength=x.shape[0])
        return variance, 1.0 - x_inv_q
    tri = np.tril(inv) if lower else np.triu(inv)
    prod = tri * gram
    return np.diag(tri).copy(), prod.sum(axis=1) + prod.sum(axis=0) - np.diag(prod)


def spd_inverse(x: np.ndarray, factor: Optional[Tuple[np.ndarray, bool]] = None) -> np.ndarray:
    """``X^-1`` from one Cholesky factorisation (given or computed); pseudo-inverse if X is singular."""
    factor = cholesky(x) if factor is None else factor
    if factor is None:
        return np.linalg.pinv(x)
    try:
        return inverse_from_cholesky(factor)
    except np.linalg.LinAlgError:
        return np.linalg.pinv(x)


def entries_bandwidth(entries: Tuple[np.ndarray, np.ndarray, np.ndarray]) -> int:
    """:func:`bandwidth` of a matrix given by its entries (:func:`sparse_entries`), in ``O(nnz)``."""
    rows, cols, _ = entries
    return int(np.abs(rows - cols).max(initial=0))


def bandwidth(x: np.ndarray) -> int:
    """Largest ``|i - j|`` with ``x[i, j] != 0`` of a square matrix (0 for a diagonal one)."""
    rows, cols = np.nonzero(x)
    return int(np.abs(rows - cols).max(initial=0))


def banded_cholesky(x: np.ndarray, band: int) -> Optional[np.ndarray]:
    """Upper banded Cholesky factor of an SPD matrix with ``x[i, j] = 0`` for ``|i - j| > band``
    (LAPACK ``pbtrf``, ``O(N b^2)``), in banded storage ``u[b - d, j] = U[j - d, j]`` (row ``b``
    is the diagonal), or ``None`` if ``x`` is not numerically positive definite."""
    n = x.shape[0]
    b = max(int(band), 1)
    ab = np.zeros((b + 1, n))
    for d in range(b + 1):  # upper banded storage: ab[b - d, j] = x[j - d, j]
        ab[b - d, d:] = np.diagonal(x, d)
    try:
        u, info = lapack.dpbtrf(ab, lower=0)
    except ValueError:
        return None
    return u if info == 0 else None


def banded_inverse_diagonal(x: np.ndarray, band: int) -> Optional[np.ndarray]:
    """``diag(X^-1)`` of an SPD matrix with ``x[i, j] = 0`` for ``|i - j| > band``, or ``None``.

    Cut into blocks of ``band`` rows, such a matrix is block tridiagonal (diagonal blocks
    ``D_i``, off-diagonal ``B_i = X[block i, block i + 1]``). The diagonal blocks of its
    inverse follow from the Schur complements of block elimination, forward
    ``S_0 = D_0``, ``S_i = D_i - B_{i-1}^T S_{i-1}^-1 B_{i-1}``, then backward
    ``G_last = S_last^-1``, ``G_i = S_i^-1 + S_i^-1 B_i G_{i+1} B_i^T S_i^-1`` (Takahashi's
    recurrence by blocks). ``O(N b^2)`` like the scalar recurrence, in ``2 N / b``
    small dense steps instead of ``N`` Python iterations. ``None`` when ``X`` is not
    numerically positive definite (the caller falls back).
    """
    n = x.shape[0]
    if n == 0:
        return np.empty(0)
    b = max(int(band), 1)
    edges = list(range(0, n, b)) + [n]
    blocks = list(zip(edges[:-1], edges[1:]))
    s_inv = []
    for i, (lo, hi) in enumerate(blocks):
        schur = np.array(x[lo:hi, lo:hi], np.float64)
        if i:
            plo, phi = blocks[i - 1]
            coupling = x[plo:phi, lo:hi]
            schur -= coupling.T @ s_inv[-1] @ coupling
        try:
            chol = np.linalg.cholesky(schur)
        except np.linalg.LinAlgError:
            return None
        chol_inv = lapack.dtrtri(chol, lower=1)[0]
        s_inv.append(chol_inv.T @ chol_inv)  # S^-1 = L^-T L^-1
    diag = np.empty(n)
    g = s_inv[-1]
    diag[blocks[-1][0]:] = np.diag(g)
    for i in range(len(blocks) - 2, -1, -1):
        (lo, hi), (nlo, nhi) = blocks[i], blocks[i + 1]
        t = s_inv[i] @ x[lo:hi, nlo:nhi]
        g = s_inv[i] + t @ g @ t.T
        diag[lo:hi] = np.diag(g)
    return diag if np.all(np.isfinite(diag)) else None
