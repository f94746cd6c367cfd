"""The constrained, regularised solve of Eq. 6.

Per colour channel k the table f (``N = n_t n_s`` nodes, column ``it * n_s + is``)
minimises

    E(f) = (1/M) ||(I_k - L_k f) / c_k||^2  +  alpha (1/N) (||Λs^-1 Ds f||^2 + ||Λt^-1 Dt f||^2),
    subject to f >= 0,

with the prior's operators and weights (:mod:`mi_bivariate.prior`). This is the
paper's Eq. 6 with two normalisations that make one alpha serve every probe, every
material and every observation count:

- ``c_k = sqrt(mean_m (sum_n L_k[m, n])^2)``: the RMS over the rows of the pixel value a
  constant table f = 1 (1/sr) would produce. It depends on L only (never on I), so a
  brighter probe (L and I both x10) leaves E, and f, unchanged, while brighter
  observations (I x10) give f x10 exactly (E is homogeneous of degree 2 in (I, f)).
- ``1/M`` and ``1/N`` make the data term a mean over observations and the prior term a
  mean over nodes (with Ds, Dt being derivatives on the unit st square, the latter
  approximates an integral, so it does not grow with the grid).

In the paper's own form the weight is ``alpha_eq6 = alpha M c_k^2 / N``.

Both terms have units of f^2 ((1/sr)^2), as the prior's sigmas are dimensionless.

The non-negative least-squares problem is solved on the normal equations
``G f = b`` (``G = L^T L / (c^2 M) + alpha/N R^T R``, float64, ``N x N``) with Kim & Park's
block principal pivoting (with Murty's single-exchange fallback), starting from the
paper's Lambertian initialisation. Every answer's KKT conditions are verified; if they
fail, the problem is re-solved with ``scipy.optimize.nnls`` on an eigen-reduced
``N x N`` system and the result says so. The solve is done once per weight pair and the
pair with the lower data residual is kept per channel (paper Sect. 4).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import scipy.linalg as sla
import scipy.optimize as sopt

from .errors import InputError
from .prior import PAIRS, Prior, default_prior

#: Default regularisation weight alpha of the normalised objective (see module docstring),
#: with the packaged default prior. Provisional, from :func:`alpha_sweep` with the error of
#: ``L_pisa f`` against ``L_pisa f_true`` (f_true: the Eq. 1 reduction) as the criterion:
#: for 4 MERL-NBRDF materials rendered in 3D with Mitsuba under grace_256 (256 px, 256 spp)
#: and recovered with :func:`mi_bivariate.recover.recover`, the mean error was 0.38, 0.15,
#: 0.099, 0.088, 0.104 at alpha = 1e-8, 3e-7, 3e-6, 1e-5, 1e-4. Noiseless bivariate inputs
#: with 1% (5%) noise prefer 1e-7 (3e-7..1e-6): model error calls for more smoothing.
DEFAULT_ALPHA = 1e-5
#: Largest accepted KKT violation (relative natural residual, see :func:`kkt_violation`).
KKT_TOLERANCE = 1e-9
# Sign threshold (relative) for moving a variable between sets: below it, a negative x
# or gradient is round-off, and exchanging it would only make the pivoting cycle.
_EXCHANGE_TOLERANCE = 1e-12
# Block exchanges allowed without progress before Murty's single exchange (Kim & Park).
_BPP_BACKUP = 3
# Passive-set solves before handing over to the fallback. Block pivoting typically needs
# 1-10 on the lighting matrices seen so far; Murty's rule alone could need up to ~N.
_MAX_ITER = 100


# ---------------------------------------------------------------------------
# NNLS on the normal equations
# ---------------------------------------------------------------------------

@dataclass
class NNLSResult:
    """Solution of ``min 1/2 x^T G x - b^T x, x >= 0``."""
    x: np.ndarray            #: (N,) float64, >= 0
    iterations: int          #: passive-set linear solves
    kkt_violation: float     #: relative, see :func:`kkt_violation`
    method: str              #: "bpp" or "bpp+nnls-fallback"


def kkt_violation(G: np.ndarray, b: np.ndarray, x: np.ndarray) -> float:
    """Relative KKT violation of ``x`` for ``min 1/2 x^T G x - b^T x, x >= 0``.

    The natural residual ``max_i |min(x_i / x_scale, g_i / g_scale)|`` with the gradient
    ``g = G x - b``: zero exactly at the solution; it measures primal infeasibility
    (x_i < 0), dual infeasibility (g_i < 0) and complementarity (both > 0) at once.
    ``x_scale = max |x|`` and ``g_scale = max |b| + max (|G| |x|)``, the size of the terms
    that cancel in g, so round-off gives ~1e-15 whatever the conditioning.
    """
    x = np.asarray(x, dtype=np.float64)
    g = G @ x - b
    x_scale = float(np.abs(x).max(initial=0.0)) or 1.0
    g_scale = float(np.abs(b).max(initial=0.0) + (np.abs(G) @ np.abs(x)).max(initial=0.0)) or 1.0
    return float(np.abs(np.minimum(x / x_scale, g / g_scale)).max(initial=0.0))


def _passive_solve(G: np.ndarray, b: np.ndarray, passive: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """x with ``G_FF x_F = b_F``, 0 elsewhere, and the gradient ``y = G x - b`` (0 on F)."""
    x = np.zeros_like(b)
    idx = np.flatnonzero(passive)
    if idx.size:
        g_ff = G[np.ix_(idx, idx)]
        try:
            factor = sla.cho_factor(g_ff, check_finite=False)
            x_f = sla.cho_solve(factor, b[idx], check_finite=False)
            if not np.all(np.isfinite(x_f)):
                raise np.linalg.LinAlgError
        except np.linalg.LinAlgError:
            # Singular sub-problem (alpha = 0 with a rank-deficient L): minimum-norm solution.
            x_f = sla.lstsq(G[np.ix_(idx, idx)], b[idx], check_finite=False)[0]
        x[idx] = x_f
    y = G @ x - b
    y[idx] = 0.0
    return x, y


def _nnls_fallback(G: np.ndarray, b: np.ndarray) -> np.ndarray:
    """scipy.optimize.nnls on ``||R x - d||`` with ``R^T R = G``, ``R^T d = b``."""
    w, v = np.linalg.eigh(G)
    keep = w > max(w.max(initial=0.0), 0.0) * G.shape[0] * np.finfo(np.float64).eps
    root = np.sqrt(w[keep])
    r = root[:, None] * v[:, keep].T
    d = (v[:, keep].T @ b) / root
    x, _ = sopt.nnls(r, d, maxiter=50 * G.shape[0])
    return np.maximum(x, 0.0)


def nnls_gram(G: np.ndarray, b: np.ndarray, passive: Optional[np.ndarray] = None, *,
              max_iter: Optional[int] = None, tol: float = KKT_TOLERANCE) -> NNLSResult:
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

    x, y = _passive_solve(G, b, passive)
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
        x, y = _passive_solve(G, b, passive)
        iterations += 1

    x = np.maximum(x, 0.0)
    violation = kkt_violation(G, b, x)
    method = "bpp"
    if not violation <= tol:
        x = _nnls_fallback(G, b)
        violation = kkt_violation(G, b, x)
        method = "bpp+nnls-fallback"
    return NNLSResult(x, iterations, violation, method)


# ---------------------------------------------------------------------------
# Data term
# ---------------------------------------------------------------------------

@dataclass
class DataTerm:
    """Normalised normal equations of the data term, per channel (reusable across
    priors and alphas, e.g. for :func:`alpha_sweep`)."""
    gram: np.ndarray        #: (3, N, N) float64, L_k^T L_k / (c_k^2 M)
    rhs: np.ndarray         #: (3, N) float64, L_k^T I_k / (c_k^2 M)
    scale: np.ndarray       #: (3,) c_k, RMS row sum of L_k (radiance * sr)
    lighting: np.ndarray    #: (M, N, 3) the caller's L (not copied)
    observations: np.ndarray  #: (M, 3) the caller's I (not copied)
    time_s: float = 0.0

    @property
    def n_rows(self) -> int:
        return self.lighting.shape[0]

    @property
    def n_nodes(self) -> int:
        return self.lighting.shape[1]


def _validate(L: np.ndarray, I: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
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


def prepare_data_term(L: np.ndarray, I: np.ndarray) -> DataTerm:
    """Validate ``L (M, N, 3)`` and ``I (M, 3)`` and build the normalised normal equations."""
    L, I = _validate(L, I)
    start = time.perf_counter()
    m, n = L.shape[:2]
    gram = np.empty((3, n, n))
    rhs = np.empty((3, n))
    scale = np.empty(3)
    for k in range(3):
        l_k = L[:, :, k].astype(np.float64)
        scale[k] = np.sqrt(np.mean(l_k.sum(axis=1) ** 2))
        if scale[k] == 0.0:
            raise InputError("lighting matrix L", f"channel {k} is all zero: the probe sheds no light in it")
        weight = 1.0 / (scale[k] ** 2 * m)
        gram[k] = (l_k.T @ l_k) * weight
        rhs[k] = (l_k.T @ I[:, k].astype(np.float64)) * weight
    return DataTerm(gram, rhs, scale, L, I, time.perf_counter() - start)


# ---------------------------------------------------------------------------
# The solve
# ---------------------------------------------------------------------------

@dataclass
class PairSolution:
    """One weight pair's solution (all arrays per channel)."""
    table: np.ndarray              #: (n_t, n_s, 3) float32, 1/sr
    data_term: np.ndarray          #: (3,) (1/M) ||(I - L f)/c||^2, (1/sr)^2
    prior_term: np.ndarray         #: (3,) (1/N)(||Λs^-1 Ds f||^2 + ||Λt^-1 Dt f||^2), without alpha
    relative_residual: np.ndarray  #: (3,) ||I - L f|| / ||I||
    iterations: np.ndarray         #: (3,) int
    kkt_violation: np.ndarray      #: (3,)
    method: Tuple[str, str, str]
    time_s: float


@dataclass
class SolveResult:
    """Result of :func:`solve`: the kept table and what led to it."""
    table: np.ndarray                  #: (n_t, n_s, 3) float32, 1/sr, winner per channel
    winner: Tuple[str, str, str]       #: "diffuse" or "gloss" per channel
    alpha: float
    relative_residual: np.ndarray      #: (3,) of the winner
    pairs: Dict[str, PairSolution]     #: every pair's solution
    lambertian: np.ndarray             #: (3,) 1/sr, the Lambertian start (best constant table)
    scale: np.ndarray                  #: (3,) data normalisation c_k
    timings: Dict[str, float] = field(default_factory=dict)  #: seconds

    @property
    def kkt_violation(self) -> np.ndarray:
        """(3,) of the winner."""
        return np.array([self.pairs[w].kkt_violation[k] for k, w in enumerate(self.winner)])

    def summary(self) -> str:
        lines = [f"alpha={self.alpha:g}  total {self.timings.get('total', 0.0):.2f} s"]
        for k, ch in enumerate("RGB"):
            parts = [f"{p}: rel.res {s.relative_residual[k]:.4g} prior {s.prior_term[k]:.3g} "
                     f"it {s.iterations[k]} kkt {s.kkt_violation[k]:.1e} {s.method[k]}"
                     for p, s in self.pairs.items()]
            lines.append(f"{ch}: winner {self.winner[k]:7s} | " + " | ".join(parts))
        return "\n".join(lines)


def _grid(n_nodes: int, prior: Prior, n_t: Optional[int], n_s: Optional[int]) -> Tuple[int, int]:
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


def _check_alpha(alpha: float) -> float:
    try:
        alpha = float(alpha)
    except (TypeError, ValueError):
        raise InputError("alpha", f"must be a number, got {alpha!r}") from None
    if not np.isfinite(alpha) or alpha < 0:
        raise InputError("alpha", f"must be finite and >= 0, got {alpha}")
    return alpha


def _solve_pair(data: DataTerm, penalty: np.ndarray, alpha: float, start: np.ndarray) -> Tuple[np.ndarray, list]:
    """(N, 3) float64 solution and the per-channel :class:`NNLSResult`."""
    n = data.n_nodes
    weight = alpha / n
    table = np.empty((n, 3))
    results = []
    for k in range(3):
        res = nnls_gram(data.gram[k] + weight * penalty, data.rhs[k], passive=np.full(n, start[k] > 0))
        table[:, k] = res.x
        results.append(res)
    return table, results


def _residual_norms(data: DataTerm, tables: Sequence[np.ndarray]) -> np.ndarray:
    """``(len(tables), 3)`` ||I_k - L_k f_k|| in float64, one pass over L per channel."""
    norms = np.empty((len(tables), 3))
    for k in range(3):
        f = np.stack([t[:, k] for t in tables], axis=1)
        predicted = data.lighting[:, :, k].astype(np.float64) @ f
        norms[:, k] = np.linalg.norm(data.observations[:, k, None].astype(np.float64) - predicted, axis=0)
    return norms


def solve_prepared(data: DataTerm, prior: Optional[Prior] = None, alpha: Optional[float] = None, *,
                   n_t: Optional[int] = None, n_s: Optional[int] = None,
                   pairs: Sequence[str] = PAIRS) -> SolveResult:
    """:func:`solve` on a prepared :class:`DataTerm`."""
    t0 = time.perf_counter()
    prior = default_prior() if prior is None else prior
    alpha = DEFAULT_ALPHA if alpha is None else _check_alpha(alpha)
    n_t, n_s = _grid(data.n_nodes, prior, n_t, n_s)
    if (prior.n_t, prior.n_s) != (n_t, n_s):
        prior = prior.resampled(n_t, n_s)
    if not pairs:
        raise InputError("pairs", "need at least one weight pair")
    ones = np.ones(data.n_nodes)
    # The paper's Lambertian start: the best constant table (the prior ignores constants).
    lambertian = np.array([max(0.0, float(ones @ data.rhs[k]) / float(ones @ data.gram[k] @ ones))
                           for k in range(3)])
    raw = {}
    for p in pairs:
        t1 = time.perf_counter()
        regulariser = prior.regulariser(p)
        penalty = (regulariser.T @ regulariser).toarray()
        raw[p] = (*_solve_pair(data, penalty, alpha, lambertian), regulariser, time.perf_counter() - t1)
    t1 = time.perf_counter()
    residuals = _residual_norms(data, [raw[p][0] for p in pairs])
    norm_i = np.linalg.norm(data.observations.astype(np.float64), axis=0)
    solutions = {}
    for j, p in enumerate(pairs):
        table, results, regulariser, elapsed = raw[p]
        r = residuals[j]
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.where(norm_i > 0, r / np.where(norm_i > 0, norm_i, 1.0), np.where(r == 0, 0.0, np.inf))
        solutions[p] = PairSolution(
            table=table.reshape(n_t, n_s, 3).astype(np.float32),
            data_term=r**2 / (data.scale**2 * data.n_rows),
            prior_term=np.sum((regulariser @ table) ** 2, axis=0) / data.n_nodes,
            relative_residual=rel,
            iterations=np.array([res.iterations for res in results]),
            kkt_violation=np.array([res.kkt_violation for res in results]),
            method=tuple(res.method for res in results),
            time_s=elapsed)
    residual_time = time.perf_counter() - t1
    winner = tuple(min(solutions, key=lambda p: (solutions[p].data_term[k], p != pairs[0]))
                   for k in range(3))
    table = np.stack([solutions[w].table[:, :, k] for k, w in enumerate(winner)], axis=-1)
    rel = np.array([solutions[w].relative_residual[k] for k, w in enumerate(winner)])
    timings = {"normal_equations": data.time_s, **{p: s.time_s for p, s in solutions.items()},
               "residuals": residual_time}
    timings["total"] = data.time_s + time.perf_counter() - t0
    return SolveResult(table, winner, alpha, rel, solutions, lambertian, data.scale.copy(), timings)


def solve(L: np.ndarray, I: np.ndarray, prior: Optional[Prior] = None, alpha: Optional[float] = None, *,
          n_t: Optional[int] = None, n_s: Optional[int] = None,
          pairs: Sequence[str] = PAIRS) -> SolveResult:
    """Recover the bivariate table from ``I = L f`` (Eq. 6), per channel, both weight pairs.

    Args:
        L: ``(M, N, 3)`` lighting matrix (float32 is fine; the solve is float64),
            column ``it * n_s + is``.
        I: ``(M, 3)`` observed pixel values (linear radiance).
        prior: weight pairs; default :func:`mi_bivariate.prior.default_prior`, resampled
            if its grid differs from ``(n_t, n_s)``.
        alpha: weight of the normalised prior term (default :data:`DEFAULT_ALPHA`).
        n_t, n_s: grid; default the prior's when it matches N, else sqrt(N).
        pairs: which pairs to solve with; the lower data residual wins per channel.

    Raises:
        InputError: shapes, NaN/inf, negative alpha, no observations, grid mismatch.
    """
    return solve_prepared(prepare_data_term(L, I), prior, alpha, n_t=n_t, n_s=n_s, pairs=pairs)


@dataclass
class SweepPoint:
    alpha: float
    result: SolveResult
    table_error: Optional[np.ndarray]  #: (3,) ||f - f_true|| / ||f_true|| per channel, if truth given


def alpha_sweep(L: np.ndarray, I: np.ndarray, alphas: Sequence[float], prior: Optional[Prior] = None, *,
                truth: Optional[np.ndarray] = None, **kwargs) -> List[SweepPoint]:
    """Solve for every alpha, building the normal equations once (for tuning alpha).

    Args:
        truth: optional ``(n_t, n_s, 3)`` reference table (e.g. the reduced ground truth);
            each point then carries its per-channel relative RMS table error.
        kwargs: passed to :func:`solve_prepared` (``n_t``, ``n_s``, ``pairs``).
    """
    data = prepare_data_term(L, I)
    prior = default_prior() if prior is None else prior
    points = []
    for alpha in alphas:
        result = solve_prepared(data, prior, alpha, **kwargs)
        error = None
        if truth is not None:
            ref = np.asarray(truth, dtype=np.float64)
            if ref.shape != result.table.shape:
                raise InputError("truth", f"shape {ref.shape} differs from the table {result.table.shape}")
            diff = (result.table - ref).reshape(-1, 3)
            error = np.linalg.norm(diff, axis=0) / np.maximum(np.linalg.norm(ref.reshape(-1, 3), axis=0), 1e-300)
        points.append(SweepPoint(float(alpha), result, error))
    return points
