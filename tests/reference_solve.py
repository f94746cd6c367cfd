"""FROZEN COPY of mi_bivariate/solve.py as of commit 1f248dd (solver v2), the reference the
faster solve package is checked against (tests/test_solve_reference.py, benchmarks/bench_speed.py).
Do not edit: it is the old code path.

Original docstring: the constrained, regularised solve of Eq. 6.

Per colour channel k the table f (``N = n_t n_s`` nodes, column ``it * n_s + is``)
minimises

    E(f) = (1/M) ||(I_k - L_k f) / sigma_k||^2  +  alpha_k (1/N) ||R f / level_k||^2
           [ + (1/M) ||(f - mean_k) / mean_std_k||^2 ],            subject to f >= 0,

with ``R`` the prior's weighted differences (``||Λs^-1 Ds f||^2 + ||Λt^-1 Dt f||^2``,
:mod:`mi_bivariate.prior`). This is the paper's Eq. 6 with three changes, each
measured (``docs/recovery.md``, "What each change brought"):

- **Noise-aware rows.** ``sigma`` is each observation's noise standard deviation
  (:func:`row_sigma`): a relative model error every prediction carries plus the
  camera's ``a I + b``. Rows are thus weighted by information, not brightness:
  several images combine by their own scale and noise (an image 50x brighter no
  longer carries 2500x the weight), dim pixels, which hold the low-valued nodes,
  count, and a noisy image is not over-fitted.
- **Scale-free alpha.** ``level_k`` is the best constant (Lambertian) table, the
  paper's starting point, so alpha is dimensionless: a brighter probe, image or
  material changes nothing. ``alpha`` is given, or chosen per channel by
  generalised cross-validation (:func:`gcv_curve`).
- **A table prior** (optional): a per-node Gaussian from the data-driven basis
  prior (:mod:`mi_bivariate.basis_prior`), which carries what measured materials do
  into the nodes the image does not pin down.

The non-negative least-squares problem is solved on the normal equations
``X f = b`` (``X = L^T W L / M + lambda R^T R [+ diag]``, float64, ``N x N``) with Kim &
Park's block principal pivoting (with Murty's single-exchange fallback), starting from
the paper's Lambertian initialisation. Every answer's KKT conditions are verified; if
they fail, the problem is re-solved with ``scipy.optimize.nnls`` on an eigen-reduced
``N x N`` system and the result says so. The solve is done once per weight pair; with
a given alpha the pair with the lower data residual is kept per channel (paper
Sect. 4), with GCV the pair with the lower GCV score. Each solution carries a per-node
confidence: the diagonal of the model resolution matrix ``X^-1 L^T W L / M`` (1: the
node's value comes from the image; 0: from the priors) and the posterior spread.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import scipy.linalg as sla
import scipy.optimize as sopt

from mi_bivariate.errors import InputError
from mi_bivariate.prior import PAIRS, Prior, default_prior

#: Default weight alpha of the normalised smoothness term (see the module docstring).
#: Chosen on 8 of the 50 *training* MERL-NBRDF materials (never on a scored one) with the
#: default model-error form and the basis prior, by the median over materials of the
#: relight error under three novel probes divided by the exact reduction's
#: (benchmarks/ablation.py, docs/recovery.md): 1.27 at 1e-2 (GCV per recovery: 1.91,
#: it over-fits the model error, which is correlated between neighbouring pixels).
DEFAULT_ALPHA = 1e-2
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
            a, b = (np.broadcast_to(np.asarray(v, np.float64), (3,)) for v in params)
            if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b)) and np.all(a >= 0) and np.all(b >= 0)):
                raise InputError("noise", f"camera noise (a, b) must be finite and >= 0, got {params}")
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


def prepare_data_term(L: np.ndarray, I: np.ndarray, sigma: Optional[np.ndarray] = None,
                      image_index: Optional[np.ndarray] = None) -> DataTerm:
    """Validate ``L (M, N, 3)`` and ``I (M, 3)`` and build the noise-weighted normal equations.

    Args:
        sigma: ``(M, 3)`` per-row noise std; default :func:`row_sigma` of ``I``
            (clean input: the model error alone), per image when ``image_index`` is given.
    """
    L, I = _validate(L, I)
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
    for k in range(3):
        w = 1.0 / (sigma[:, k] * np.sqrt(m))
        a_k = L[:, :, k].astype(np.float64) * w[:, None]
        y_k = I[:, k].astype(np.float64) * w
        if not np.any(a_k):
            raise InputError("lighting matrix L", f"channel {k} is all zero: the probe sheds no light in it")
        gram[k] = a_k.T @ a_k
        rhs[k] = a_k.T @ y_k
        yy[k] = y_k @ y_k
        level[k] = max(0.0, float(ones @ rhs[k]) / float(ones @ gram[k] @ ones))
    return DataTerm(gram, rhs, yy, level, sigma, L, I, time.perf_counter() - start)


# ---------------------------------------------------------------------------
# Choosing alpha: generalised cross-validation
# ---------------------------------------------------------------------------

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


def _penalty_weight(alpha: float, data: DataTerm, k: int) -> float:
    """lambda = alpha / (N level_k^2): the prior term's weight in the normal equations."""
    level = data.level[k] if data.level[k] > 0 else 1.0
    return alpha / (data.n_nodes * level * level)


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
        lam = _penalty_weight(alpha, data, k)
        x = g + lam * penalty
        x[np.diag_indices(n)] += fixed
        factor = sla.cho_factor(x, check_finite=False)
        f = sla.cho_solve(factor, b + shift, check_finite=False)
        rho = max(data.yy[k] - 2.0 * f @ b + f @ g @ f, 0.0)
        # tr(X^-1 gram) = N - tr(X^-1 (lam P + diag(fixed)))
        other = lam * pz + fixed[:, None] * z
        trace = n - float(np.mean(np.sum(z * sla.cho_solve(factor, other, check_finite=False), axis=0)))
        dof = float(np.clip(trace, 0.0, min(n, m - 1)))
        dofs.append(dof)
        scores.append(rho / (1.0 - dof / m) ** 2)
    alphas = np.asarray(alphas, dtype=np.float64)
    scores = np.asarray(scores)
    i = int(np.argmin(scores))
    best, score = float(alphas[i]), float(scores[i])
    if 0 < i < len(alphas) - 1:
        x = np.log10(alphas[i - 1:i + 2])
        y = np.log(scores[i - 1:i + 2])
        c2, c1, c0 = np.polyfit(x, y, 2)
        if c2 > 0:
            x_min = float(np.clip(-c1 / (2 * c2), x[0], x[2]))
            best, score = 10.0 ** x_min, float(np.exp(np.polyval([c2, c1, c0], x_min)))
    return GCVCurve(alphas, scores, np.asarray(dofs), best, score)


# ---------------------------------------------------------------------------
# The solve
# ---------------------------------------------------------------------------

@dataclass
class PairSolution:
    """One weight pair's solution (all arrays per channel)."""
    table: np.ndarray              #: (n_t, n_s, 3) float32, 1/sr
    alpha: np.ndarray              #: (3,) the alpha used per channel
    gcv: np.ndarray                #: (3,) GCV score at that alpha (NaN when alpha was given)
    data_term: np.ndarray          #: (3,) (1/M) ||(I - L f)/sigma||^2 (dimensionless)
    prior_term: np.ndarray         #: (3,) (1/N) ||R f / level||^2, without alpha
    relative_residual: np.ndarray  #: (3,) ||I - L f|| / ||I||
    resolution: np.ndarray         #: (n_t, n_s, 3) diag of X^-1 gram (the model resolution matrix)
    posterior_std: np.ndarray      #: (n_t, n_s, 3) 1/sr, sqrt(diag(X^-1) / M) (unconstrained)
    measured: np.ndarray           #: (n_t, n_s, 3) 1 - posterior var / prior-only var: 1 = the image set it
    iterations: np.ndarray         #: (3,) int
    kkt_violation: np.ndarray      #: (3,)
    method: Tuple[str, str, str]
    time_s: float


@dataclass
class SolveResult:
    """Result of :func:`solve`: the kept table and what led to it."""
    table: np.ndarray                  #: (n_t, n_s, 3) float32, 1/sr, winner per channel
    winner: Tuple[str, str, str]       #: "diffuse" or "gloss" per channel
    alphas: np.ndarray                 #: (3,) alpha per channel (of the winner)
    relative_residual: np.ndarray      #: (3,) of the winner
    pairs: Dict[str, PairSolution]     #: every pair's solution
    lambertian: np.ndarray             #: (3,) 1/sr, the Lambertian start (best constant table)
    scale: np.ndarray                  #: (3,) the prior's scale (the Lambertian level)
    alpha_rule: str = "gcv"            #: "gcv" or "given"
    timings: Dict[str, float] = field(default_factory=dict)  #: seconds

    @property
    def alpha(self) -> float:
        """The median of :attr:`alphas` (one number for summaries)."""
        return float(np.median(self.alphas))

    def _of_winner(self, name: str) -> np.ndarray:
        return np.stack([getattr(self.pairs[w], name)[..., k] for k, w in enumerate(self.winner)], axis=-1)

    @property
    def resolution(self) -> np.ndarray:
        """(n_t, n_s, 3) per-node share of the data in the estimate (see :class:`PairSolution`)."""
        return self._of_winner("resolution")

    @property
    def posterior_std(self) -> np.ndarray:
        """(n_t, n_s, 3) 1/sr."""
        return self._of_winner("posterior_std")

    @property
    def measured(self) -> np.ndarray:
        """(n_t, n_s, 3) in [0, 1]: how much of each node's uncertainty the image removed."""
        return self._of_winner("measured")

    @property
    def kkt_violation(self) -> np.ndarray:
        """(3,) of the winner."""
        return np.array([self.pairs[w].kkt_violation[k] for k, w in enumerate(self.winner)])

    def summary(self) -> str:
        lines = [f"alpha ({self.alpha_rule}) R/G/B {' '.join(f'{a:.3g}' for a in self.alphas)}  "
                 f"total {self.timings.get('total', 0.0):.2f} s"]
        for k, ch in enumerate("RGB"):
            parts = [f"{p}: alpha {s.alpha[k]:.3g} gcv {s.gcv[k]:.4g} rel.res {s.relative_residual[k]:.4g} "
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


def _check_alpha(alpha) -> Optional[float]:
    """``None`` for "choose by GCV" (``"gcv"``), :data:`DEFAULT_ALPHA` for ``None``, else a finite alpha >= 0."""
    if alpha is None:
        return DEFAULT_ALPHA
    if isinstance(alpha, str) and alpha == "gcv":
        return None
    try:
        alpha = float(alpha)
    except (TypeError, ValueError):
        raise InputError("alpha", f"must be a number or 'gcv', got {alpha!r}") from None
    if not np.isfinite(alpha) or alpha < 0:
        raise InputError("alpha", f"must be finite and >= 0, got {alpha}")
    return alpha


def _solve_pair(data: DataTerm, regulariser, alpha: Optional[float], n_t: int, n_s: int,
                start: np.ndarray, mean: Optional[np.ndarray] = None,
                mean_std: Optional[np.ndarray] = None) -> PairSolution:
    """One weight pair, every channel: alpha (GCV unless given), NNLS, per-node confidence.

    ``mean``, ``mean_std`` ``(N, 3)`` (1/sr): a diagonal Gaussian prior on the table
    (the basis prior), added as ``(1/M) sum_n ((f_n - mean_n) / mean_std_n)^2``.
    """
    t0 = time.perf_counter()
    n, m = data.n_nodes, data.n_rows
    penalty = (regulariser.T @ regulariser).toarray()
    table = np.empty((n, 3))
    alphas, scores = np.empty(3), np.full(3, np.nan)
    resolution, post_std, measured = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3))
    results = []
    for k in range(3):
        extra = None
        if mean is not None:
            precision = 1.0 / (m * np.maximum(mean_std[:, k], 1e-30) ** 2)
            extra = (precision, precision * mean[:, k])
        if alpha is None:
            curve = gcv_curve(data, penalty, k, extra=extra)
            alphas[k], scores[k] = curve.alpha, curve.score
        else:
            alphas[k] = alpha
        lam = _penalty_weight(alphas[k], data, k)
        x = data.gram[k] + lam * penalty
        rhs = data.rhs[k]
        if extra is not None:
            x[np.diag_indices(n)] += extra[0]
            rhs = rhs + extra[1]
        res = nnls_gram(x, rhs, passive=np.full(n, start[k] > 0) if mean is None else mean[:, k] > 0)
        table[:, k] = res.x
        results.append(res)
        # Per-node confidence from the unconstrained posterior at this alpha.
        try:
            inverse = sla.cho_solve(sla.cho_factor(x, check_finite=False), np.eye(n), check_finite=False)
        except np.linalg.LinAlgError:
            inverse = np.linalg.pinv(x)
        resolution[:, k] = np.clip(np.einsum("ij,ji->i", inverse, data.gram[k]), 0.0, 1.0)
        post_std[:, k] = np.sqrt(np.maximum(np.diag(inverse), 0.0) / m)
        # How much the image narrowed each node: 1 - var(posterior) / var(priors alone). The
        # smoothness prior alone is improper (constants are free), so a ridge of 1e-6 of the
        # data's mean diagonal stands in where no table prior is given.
        prior_x = lam * penalty
        ridge = extra[0] if extra is not None else np.full(n, 1e-6 * float(np.mean(np.diag(data.gram[k]))))
        prior_x[np.diag_indices(n)] += ridge
        try:
            prior_var = np.diag(sla.cho_solve(sla.cho_factor(prior_x, check_finite=False), np.eye(n),
                                              check_finite=False))
        except np.linalg.LinAlgError:
            prior_var = np.diag(np.linalg.pinv(prior_x))
        measured[:, k] = np.clip(1.0 - np.diag(inverse) / np.maximum(prior_var, 1e-300), 0.0, 1.0)
    f = table
    data_term = np.array([data.yy[k] - 2 * f[:, k] @ data.rhs[k] + f[:, k] @ data.gram[k] @ f[:, k]
                          for k in range(3)])
    level = np.where(data.level > 0, data.level, 1.0)
    prior_term = np.sum((regulariser @ f) ** 2, axis=0) / (n * level**2)
    predicted = np.einsum("mnc,nc->mc", data.lighting, f.astype(data.lighting.dtype), optimize=True)
    norm_i = np.linalg.norm(data.observations.astype(np.float64), axis=0)
    r = np.linalg.norm(data.observations.astype(np.float64) - predicted, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(norm_i > 0, r / np.where(norm_i > 0, norm_i, 1.0), np.where(r == 0, 0.0, np.inf))
    return PairSolution(
        table=table.reshape(n_t, n_s, 3).astype(np.float32), alpha=alphas, gcv=scores,
        data_term=np.maximum(data_term, 0.0), prior_term=prior_term, relative_residual=rel,
        resolution=resolution.reshape(n_t, n_s, 3), posterior_std=post_std.reshape(n_t, n_s, 3),
        measured=measured.reshape(n_t, n_s, 3),
        iterations=np.array([res.iterations for res in results]),
        kkt_violation=np.array([res.kkt_violation for res in results]),
        method=tuple(res.method for res in results), time_s=time.perf_counter() - t0)


def solve_prepared(data: DataTerm, prior: Optional[Prior] = None, alpha=None, *,
                   n_t: Optional[int] = None, n_s: Optional[int] = None,
                   pairs: Sequence[str] = PAIRS, mean: Optional[np.ndarray] = None,
                   mean_std: Optional[np.ndarray] = None) -> SolveResult:
    """:func:`solve` on a prepared :class:`DataTerm`."""
    t0 = time.perf_counter()
    prior = default_prior() if prior is None else prior
    alpha = _check_alpha(alpha)
    n_t, n_s = _grid(data.n_nodes, prior, n_t, n_s)
    if (prior.n_t, prior.n_s) != (n_t, n_s):
        prior = prior.resampled(n_t, n_s)
    if not pairs:
        raise InputError("pairs", "need at least one weight pair")
    if (mean is None) != (mean_std is None):
        raise InputError("mean", "mean and mean_std go together")
    if mean is not None:
        mean = np.asarray(mean, np.float64).reshape(data.n_nodes, 3)
        mean_std = np.asarray(mean_std, np.float64).reshape(data.n_nodes, 3)
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(mean_std)) and np.all(mean_std > 0)):
            raise InputError("mean", "the table prior's mean and std must be finite (std > 0)")
    solutions = {p: _solve_pair(data, prior.regulariser(p), alpha, n_t, n_s, data.level, mean, mean_std)
                 for p in pairs}
    if alpha is None:
        # The pair whose prior explains the image better in the cross-validation sense.
        winner = tuple(min(solutions, key=lambda p: (solutions[p].gcv[k], p != pairs[0])) for k in range(3))
    else:
        # The paper's rule: the lower data residual.
        winner = tuple(min(solutions, key=lambda p: (solutions[p].data_term[k], p != pairs[0])) for k in range(3))
    table = np.stack([solutions[w].table[:, :, k] for k, w in enumerate(winner)], axis=-1)
    rel = np.array([solutions[w].relative_residual[k] for k, w in enumerate(winner)])
    alphas = np.array([solutions[w].alpha[k] for k, w in enumerate(winner)])
    timings = {"normal_equations": data.time_s, **{p: s.time_s for p, s in solutions.items()}}
    timings["total"] = data.time_s + time.perf_counter() - t0
    return SolveResult(table, winner, alphas, rel, solutions, data.level.copy(), data.level.copy(),
                       "gcv" if alpha is None else "given", timings)


def solve(L: np.ndarray, I: np.ndarray, prior: Optional[Prior] = None, alpha=None, *,
          sigma: Optional[np.ndarray] = None, image_index: Optional[np.ndarray] = None,
          n_t: Optional[int] = None, n_s: Optional[int] = None,
          pairs: Sequence[str] = PAIRS, mean: Optional[np.ndarray] = None,
          mean_std: Optional[np.ndarray] = None) -> SolveResult:
    """Recover the bivariate table from ``I = L f`` (Eq. 6), per channel, every weight pair.

    Minimises ``(1/M) ||(I - L f) / sigma||^2 + alpha (1/N) ||R f / level||^2``, f >= 0,
    per channel, where ``sigma`` is each row's noise (:func:`row_sigma`), ``R`` the
    prior's weighted differences and ``level`` the best constant table (so alpha is
    dimensionless and a brighter image or probe changes nothing).

    Args:
        L: ``(M, N, 3)`` lighting matrix (float32 is fine; the solve is float64),
            column ``it * n_s + is``.
        I: ``(M, 3)`` observed pixel values (linear radiance).
        prior: weight pairs; default :func:`mi_bivariate.prior.default_prior`, resampled
            if its grid differs from ``(n_t, n_s)``.
        alpha: the smoothness prior's weight: a number (default :data:`DEFAULT_ALPHA`),
            and the pair with the lower data residual wins (the paper's rule); or
            ``"gcv"``: chosen per channel and pair by generalised cross-validation
            (:func:`gcv_curve`), and the pair with the lower GCV score wins.
        sigma: ``(M, 3)`` per-row noise std (default: :func:`row_sigma` of ``I``).
        image_index: ``(M,)`` image of each row (for the default ``sigma``).
        n_t, n_s: grid; default the prior's when it matches N, else sqrt(N).
        pairs: which pairs to solve with.
        mean, mean_std: ``(n_t, n_s, 3)`` 1/sr, a per-node Gaussian prior on the
            table (:meth:`mi_bivariate.basis_prior.BasisPrior.predict`), added as
            ``(1/M) sum ((f - mean) / mean_std)^2``.

    Raises:
        InputError: shapes, NaN/inf, negative alpha, no observations, grid mismatch.
    """
    return solve_prepared(prepare_data_term(L, I, sigma, image_index), prior, alpha,
                          n_t=n_t, n_s=n_s, pairs=pairs, mean=mean, mean_std=mean_std)


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
