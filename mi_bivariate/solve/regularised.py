"""The front door of the solve: every channel and prior variant of Eq. 6, the kept table.

:func:`solve` validates once (:func:`~mi_bivariate.solve.data_term.prepare_data_term`),
then :func:`solve_prepared` solves each prior variant (weight pair) per channel with the
algorithms of this package (alpha per channel by the discrepancy principle,
:mod:`~mi_bivariate.solve.discrepancy`, unless given or asked of :mod:`~mi_bivariate.solve.gcv`;
the constrained solve by :mod:`~mi_bivariate.solve.nnls`, the confidence by
:mod:`~mi_bivariate.solve.confidence`) and keeps, per channel, the pair under which the
image is likelier (:mod:`~mi_bivariate.solve.evidence`; the paper's lower data residual on
request) or, with GCV, the lower GCV score.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from mi_bivariate.errors import InputError
from mi_bivariate.prior import PAIRS, Prior, default_prior
from mi_bivariate.solve.common import (
    add_entries,
    check_alpha,
    entries_bandwidth,
    grid_shape,
    penalty_weight,
    quadratic_form,
)
from mi_bivariate.solve.confidence import NAMES as CONFIDENCE_NAMES
from mi_bivariate.solve.confidence import Confidence
from mi_bivariate.solve.data_term import DataTerm, prepare_data_term
from mi_bivariate.solve.discrepancy import DiscrepancyChoice, discrepancy_alpha
from mi_bivariate.solve.evidence import (
    DEFAULT_PAIR_RULE,
    channel_log_evidence,
    check_pair_rule,
    log_det_spd,
    penalty_log_pdet,
)
from mi_bivariate.solve.gcv import gcv_curve
from mi_bivariate.solve.nnls import NNLSResult, nnls_gram
from mi_bivariate.threads import solve_threads, thread_map

#: Memory the solve's channel workers may hold together (bytes): a 32 x 32 grid's channel peaks at
#: ~40 MB (any number of workers), a 64 x 64 grid's at ~640 MB (one worker, as before threads).
SOLVE_MEMORY = 1 << 30


@dataclass
class PairSolution:
    """One weight pair's solution (all arrays per channel).

    The confidence maps (:attr:`resolution`, :attr:`posterior_std`, :attr:`measured`) are
    computed on first access (:class:`~mi_bivariate.solve.confidence.Confidence`).
    """
    table: np.ndarray              #: (n_t, n_s, 3) float32, 1/sr
    alpha: np.ndarray              #: (3,) the alpha used per channel
    gcv: np.ndarray                #: (3,) GCV score at that alpha (NaN when alpha was given)
    data_term: np.ndarray          #: (3,) (1/M) ||(I - L f)/sigma||^2 (dimensionless)
    prior_term: np.ndarray         #: (3,) (1/N) ||R f / level||^2, without alpha
    relative_residual: np.ndarray  #: (3,) ||I - L f|| / ||I|| (NaN after ``solve_prepared(residuals=False)``)
    iterations: np.ndarray         #: (3,) int
    kkt_violation: np.ndarray      #: (3,)
    method: Tuple[str, str, str]
    time_s: float                  #: its channels' solve times summed (they run concurrently)
    confidence: Confidence = field(repr=False)
    #: (3,) log evidence of the image under this pair (:mod:`~mi_bivariate.solve.evidence`,
    #: up to a constant shared by the pairs); NaN where the pair rule did not need it
    log_evidence: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    #: ``(M, 3)`` in L's dtype: ``L f`` per channel (:func:`channel_prediction`; ``None`` after
    #: ``solve_prepared(residuals=False)``)
    predicted: Optional[np.ndarray] = field(default=None, repr=False)

    @property
    def resolution(self) -> np.ndarray:
        """(n_t, n_s, 3) diag of X^-1 gram (the model resolution matrix)."""
        return self.confidence.map("resolution")

    @property
    def posterior_std(self) -> np.ndarray:
        """(n_t, n_s, 3) 1/sr, sqrt(diag(X^-1) / M) (unconstrained)."""
        return self.confidence.map("posterior_std")

    @property
    def measured(self) -> np.ndarray:
        """(n_t, n_s, 3) 1 - posterior var / prior-only var: 1 = the image set it."""
        return self.confidence.map("measured")


@dataclass
class SolveResult:
    """Result of :func:`solve`: the kept table and what led to it."""
    table: np.ndarray                  #: (n_t, n_s, 3) float32, 1/sr, winner per channel
    winner: Tuple[str, str, str]       #: "diffuse" or "gloss" per channel (see ``pair_rule``)
    alphas: np.ndarray                 #: (3,) alpha per channel (of the winner)
    relative_residual: np.ndarray      #: (3,) of the winner
    pairs: Dict[str, PairSolution]     #: every pair's solution
    lambertian: np.ndarray             #: (3,) 1/sr, the Lambertian start (best constant table)
    scale: np.ndarray                  #: (3,) the prior's scale (the Lambertian level)
    alpha_rule: str = "discrepancy"    #: "discrepancy", "gcv" or "given"
    #: seconds: ``normal_equations``, ``total`` (wall), and per pair the sum of its channels' solve times
    #: (the channels run concurrently, so these can add up to more than the wall time)
    timings: Dict[str, float] = field(default_factory=dict)
    #: how the discrepancy principle chose alpha (``None`` for another rule)
    alpha_choice: Optional[DiscrepancyChoice] = None
    #: how the pair was kept per channel: "evidence", "residual", "gcv" or "given"
    pair_rule: str = DEFAULT_PAIR_RULE

    @property
    def alpha(self) -> float:
        """The median of :attr:`alphas` (one number for summaries)."""
        return float(np.median(self.alphas))

    def _of_winner(self, name: str) -> np.ndarray:
        shape = self.table.shape[:2]
        return np.stack([self.pairs[w].confidence.channel(name, k).reshape(shape)
                         for k, w in enumerate(self.winner)], axis=-1)

    @property
    def predicted(self) -> Optional[np.ndarray]:
        """``(M, 3)`` in L's dtype: ``L f`` of the kept table (each channel from its winner), as the solve
        computed it for the residuals; ``None`` where it did not (``solve_prepared(residuals=False)``)."""
        columns = [self.pairs[w].predicted for w in self.winner]
        if any(c is None for c in columns):
            return None
        return np.stack([c[:, k] for k, c in enumerate(columns)], axis=-1)

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
        lines = [f"alpha ({self.alpha_rule}) R/G/B {' '.join(f'{a:.3g}' for a in self.alphas)}, "
                 f"pair kept by {self.pair_rule}  "
                 f"total {self.timings.get('total', 0.0):.2f} s"]
        for k, ch in enumerate("RGB"):
            parts = [f"{p}: alpha {s.alpha[k]:.3g} gcv {s.gcv[k]:.4g} log ev {s.log_evidence[k]:.6g} "
                     f"rel.res {s.relative_residual[k]:.4g} "
                     f"it {s.iterations[k]} kkt {s.kkt_violation[k]:.1e} {s.method[k]}"
                     for p, s in self.pairs.items()]
            lines.append(f"{ch}: winner {self.winner[k]:7s} | " + " | ".join(parts))
        return "\n".join(lines)


@dataclass
class _ChannelSolve:
    """One prior variant, one channel: the NNLS answer and what led to it."""
    result: NNLSResult
    system: np.ndarray     #: X, (N, N)
    alpha: float
    gcv: float
    lam: float
    data_term: float
    objective: float  #: Phi: the data term plus every prior term at the solution
    residual: float   #: ||I - L f||, unweighted (float32 products, as the tables are stored); NaN if not computed
    predicted: Optional[np.ndarray] = None  #: (M,) L f in L's dtype, where the residual was computed

    def log_det(self) -> float:
        """``log det`` of the system (from the NNLS solve's own factorisation when it had one)."""
        return self.result.log_det if self.result.log_det is not None else log_det_spd(self.system)


def channel_prediction(data: DataTerm, k: int, f: np.ndarray) -> np.ndarray:
    """``(M,)`` ``L_k f`` of channel ``k`` in L's dtype (float32 products, as tables are stored).

    Channel ``k`` of a C-contiguous ``(M, N, 3)`` L is read as BLAS reads a matrix: L's ``(M, 3N)`` rows
    times a vector holding ``f`` in every third entry (products with exact zeros change no sum). numpy's
    product of the strided ``(M, N)`` view itself runs its own loop without BLAS: 8.2-8.6 ms against
    4.8-5.2 ms for the bench sphere's L (M 6564, 32 x 32; medians of 15), and ~6x further from the
    float64 product (largest difference 9.5e-7 against 1.7e-7 of the largest entry).
    """
    lighting = data.lighting
    f = np.asarray(f).astype(lighting.dtype)
    if not lighting.flags.c_contiguous:
        return lighting[:, :, k] @ f
    m, n, c = lighting.shape
    spread = np.zeros(n * c, lighting.dtype)
    spread[k::c] = f
    return lighting.reshape(m, n * c) @ spread


def _solve_channel(data: DataTerm, penalty: np.ndarray, alpha: Optional[float], k: int, start: np.ndarray,
                   precision: Optional[np.ndarray], mean: Optional[np.ndarray], entries: tuple,
                   factor: Optional[tuple] = None, residual: bool = True) -> _ChannelSolve:
    """Alpha (GCV unless given) and the constrained solve of one variant and channel.

    ``entries``: ``penalty``'s non-zero entries (:func:`~mi_bivariate.solve.common.sparse_entries`).
    ``factor``: the Cholesky factor of this very system if the caller has it (the discrepancy
    principle's at the alpha it chose, built by the same operations).
    ``residual``: compute ``L f`` (:func:`channel_prediction`) and ``||I - L f||``; else the residual is NaN.

    ``precision``, ``mean`` ``(N, 3)``: the diagonal Gaussian table prior (the basis prior),
    added as ``(1/M) sum_n ((f_n - mean_n) / mean_std_n)^2`` with ``precision = 1 / (M std^2)``.
    """
    n = data.n_nodes
    extra = None if precision is None else (precision[:, k], precision[:, k] * mean[:, k])
    score = np.nan
    if alpha is None:
        curve = gcv_curve(data, penalty, k, extra=extra)
        alpha, score = curve.alpha, curve.score
    lam = penalty_weight(alpha, n, data.level[k])
    x = add_entries(data.gram[k].copy(), entries, lam)
    rhs = data.rhs[k]
    if extra is not None:
        x[np.diag_indices(n)] += extra[0]
        rhs = rhs + extra[1]
    res = nnls_gram(x, rhs, passive=np.full(n, start[k] > 0) if mean is None else mean[:, k] > 0, factor=factor)
    f = res.x
    data_term = max(float(data.yy[k] - 2 * f @ data.rhs[k] + f @ data.gram[k] @ f), 0.0)
    objective = data_term + lam * quadratic_form(entries, f)
    if extra is not None:
        objective += float(np.sum(extra[0] * (f - mean[:, k]) ** 2))
    # The residual, here on the channel's worker thread (the products release the GIL).
    predicted = channel_prediction(data, k, f) if residual else None
    norm = np.nan if predicted is None else float(np.linalg.norm(data.observations[:, k].astype(np.float64)
                                                                   - predicted))
    return _ChannelSolve(res, x, float(alpha), float(score), lam, data_term, objective, norm, predicted)


def _pair_solution(data: DataTerm, regulariser, channels: List[_ChannelSolve], confidence: Confidence,
                   grid: Tuple[int, int], seconds: float, evidence: Sequence[Optional[float]]) -> PairSolution:
    """Assemble one variant's three channels, with its residuals."""
    n = data.n_nodes
    f = np.stack([c.result.x for c in channels], axis=-1)
    level = np.where(data.level > 0, data.level, 1.0)
    prior_term = np.sum((regulariser @ f) ** 2, axis=0) / (n * level**2)
    norm_i = np.linalg.norm(data.observations.astype(np.float64), axis=0)
    r = np.array([c.residual for c in channels])
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(np.isnan(r), np.nan, np.where(norm_i > 0, r / np.where(norm_i > 0, norm_i, 1.0),
                                                        np.where(r == 0, 0.0, np.inf)))
    return PairSolution(
        table=f.reshape(*grid, 3).astype(np.float32), alpha=np.array([c.alpha for c in channels]),
        gcv=np.array([c.gcv for c in channels]),
        data_term=np.maximum(np.array([c.data_term for c in channels]), 0.0), prior_term=prior_term,
        relative_residual=rel, iterations=np.array([c.result.iterations for c in channels]),
        kkt_violation=np.array([c.result.kkt_violation for c in channels]),
        method=tuple(c.result.method for c in channels), time_s=seconds, confidence=confidence,
        log_evidence=np.array([np.nan if e is None else e for e in evidence]),
        predicted=None if any(c.predicted is None for c in channels) else np.stack([c.predicted for c in channels],
                                                                                   axis=-1))


def solve_prepared(data: DataTerm, prior: Optional[Prior] = None, alpha=None, *,
                   n_t: Optional[int] = None, n_s: Optional[int] = None,
                   pairs: Sequence[str] = PAIRS, mean: Optional[np.ndarray] = None,
                   mean_std: Optional[np.ndarray] = None, pair_rule: str = DEFAULT_PAIR_RULE,
                   winner: Optional[Sequence[str]] = None,
                   maps: Sequence[str] = ("resolution",), residuals: bool = True) -> SolveResult:
    """:func:`solve` on a prepared :class:`~mi_bivariate.solve.data_term.DataTerm`.

    Channel by channel: every prior variant is solved, the kept one is chosen, and its
    posterior (resolution, posterior spread) is computed from the NNLS solve's own
    factorisation; the other variants' confidence, and ``measured``, on first access.
    The channels run on worker threads (:func:`~mi_bivariate.threads.thread_map`); each holds
    its own systems and factors (2 per variant) until its kept variant's posterior is computed.

    ``maps``: the kept variant's confidence maps (:data:`~mi_bivariate.solve.confidence.NAMES`)
    computed on the channels' threads; ``resolution`` brings ``posterior_std`` with it, and any
    other is computed on first access.

    ``residuals``: compute every variant's ``||I - L f||`` (its ``relative_residual``: one product
    with L per variant and channel, no rule uses it). ``False`` leaves them NaN, for a stage whose
    tables are only a step to another (:func:`~mi_bivariate.solve.stages.solve_stages`' first).
    """
    t0 = time.perf_counter()
    prior = default_prior() if prior is None else prior
    rule = check_alpha(alpha)
    check_pair_rule(pair_rule)
    maps = (maps,) if isinstance(maps, str) else tuple(maps)
    if any(name not in CONFIDENCE_NAMES for name in maps):
        raise InputError("maps", f"unknown confidence maps {tuple(maps)}", f"use some of {', '.join(CONFIDENCE_NAMES)}")
    maps = ("resolution",) + tuple(name for name in maps if name != "resolution")  # the posterior first
    if winner is not None:
        winner = tuple(winner)
        if len(winner) != 3 or any(w not in pairs for w in winner):
            raise InputError("winner", f"must name one of the solved pairs {tuple(pairs)} per channel, got {winner}")
    n_t, n_s = grid_shape(data.n_nodes, prior, n_t, n_s)
    if (prior.n_t, prior.n_s) != (n_t, n_s):
        prior = prior.resampled(n_t, n_s)
    if not pairs:
        raise InputError("pairs", "need at least one weight pair")
    if (mean is None) != (mean_std is None):
        raise InputError("mean", "mean and mean_std go together")
    precision = None
    if mean is not None:
        mean = np.asarray(mean, np.float64).reshape(data.n_nodes, 3)
        mean_std = np.asarray(mean_std, np.float64).reshape(data.n_nodes, 3)
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(mean_std)) and np.all(mean_std > 0)):
            raise InputError("mean", "the table prior's mean and std must be finite (std > 0)")
        precision = 1.0 / (data.n_rows * np.maximum(mean_std, 1e-30) ** 2)
    regularisers = {p: prior.regulariser(p) for p in pairs}
    sparse = {p: (r.T @ r).tocoo() for p, r in regularisers.items()}
    penalties = {p: m.toarray() for p, m in sparse.items()}
    entries = {p: (m.row, m.col, m.data) for p, m in sparse.items()}
    channels: Dict[str, List[_ChannelSolve]] = {p: [] for p in pairs}
    seconds = {p: 0.0 for p in pairs}
    confidences = {p: Confidence(data, penalties[p], np.zeros(3), precision, (n_t, n_s), entries[p])
                   for p in pairs}
    kept: List[str] = []
    evidence: Dict[str, List[Optional[float]]] = {p: [] for p in pairs}
    use_evidence = winner is None and pair_rule == "evidence" and len(pairs) > 1 and not (
        isinstance(rule, str) and rule == "gcv")
    pdets = ({p: penalty_log_pdet(penalties[p], entries_bandwidth(entries[p])) for p in pairs}
             if use_evidence and precision is None else {})
    # The channels are independent; their LAPACK runs without the GIL (mi_bivariate.solve.lapack).
    # Each holds ~5 N x N float64 arrays at its peak: as many workers as SOLVE_MEMORY allows.
    workers = min(solve_threads(), max(1, SOLVE_MEMORY // (5 * 8 * data.n_nodes**2)))
    choice: Optional[DiscrepancyChoice] = None
    if isinstance(rule, str) and rule == "discrepancy":  # one alpha for every channel, on the first pair's curve
        extra = None if precision is None else (precision, precision * mean)
        # Its factors are handed to stage 1 only when every channel takes its own at once: with fewer
        # workers the waiting channels' factors would add to the peak memory.
        choice = discrepancy_alpha(data, penalties[pairs[0]], extra=extra, entries=entries[pairs[0]],
                                   keep_factors=workers >= 3)
    def channel(k: int) -> Tuple[Dict[str, _ChannelSolve], Dict[str, float], Dict[str, Optional[float]], str]:
        """Every pair's solve of channel ``k``, their evidence, the kept pair, and its posterior while its
        factorisation is at hand (the other pairs' systems and factors are dropped)."""
        if choice is not None:
            alpha_k = choice.alpha
        elif isinstance(rule, str):
            alpha_k = None  # GCV, per channel and pair
        else:
            alpha_k = float(rule[k])
        solves: Dict[str, _ChannelSolve] = {}
        times: Dict[str, float] = {}
        for p in pairs:
            t1 = time.perf_counter()
            factor = None
            if p == pairs[0] and choice is not None and choice.factors is not None:
                # The discrepancy principle factorised this system at the alpha it chose: taken, not copied.
                factor, choice.factors[k] = choice.factors[k], None
            solves[p] = _solve_channel(data, penalties[p], alpha_k, k, data.level, precision, mean, entries[p],
                                       factor, residuals)
            times[p] = time.perf_counter() - t1
        logev = {p: None if not use_evidence else channel_log_evidence(
            solves[p].objective, data.n_rows, solves[p].log_det(), solves[p].lam, penalties[p], pdets.get(p),
            None if precision is None else precision[:, k], None if mean is None else mean[:, k]) for p in pairs}
        if winner is not None:
            w = winner[k]
        elif isinstance(rule, str) and rule == "gcv":
            # The pair whose prior explains the image better in the cross-validation sense.
            w = min(pairs, key=lambda p: (solves[p].gcv, p != pairs[0]))
        elif use_evidence:
            # The pair under whose prior the image is likelier (fit and Occam factor together).
            w = max(pairs, key=lambda p: (logev[p], p == pairs[0]))
        else:
            # The paper's rule: the lower data residual.
            w = min(pairs, key=lambda p: (solves[p].data_term, p != pairs[0]))
        for p in sorted(pairs, key=lambda p: p == w):  # the other pairs' systems and factors go first
            c = solves[p]
            confidences[p].set_weight(k, c.lam)
            if p == w:  # while its factorisation is at hand
                confidences[p].keep_factor(k, c.result.factor, c.system)
                for name in maps:
                    confidences[p].channel(name, k)
            c.result.factor, c.system = None, None
        return solves, times, logev, w

    for solves, times, logev, w in thread_map(channel, range(3), workers):
        for p in pairs:
            channels[p].append(solves[p])
            seconds[p] += times[p]
            evidence[p].append(logev[p])
        kept.append(w)
    if choice is not None:
        choice.factors = None  # used (or not needed): never kept with the result
    solutions = {p: _pair_solution(data, regularisers[p], channels[p], confidences[p], (n_t, n_s), seconds[p],
                                   evidence[p]) for p in pairs}
    kept_rule = ("given" if winner is not None else "gcv" if isinstance(rule, str) and rule == "gcv"
                 else pair_rule if len(pairs) > 1 else "given")
    winner = tuple(kept)
    table = np.stack([solutions[w].table[:, :, k] for k, w in enumerate(winner)], axis=-1)
    rel = np.array([solutions[w].relative_residual[k] for k, w in enumerate(winner)])
    alphas = np.array([solutions[w].alpha[k] for k, w in enumerate(winner)])
    timings = {"normal_equations": data.time_s, **seconds}
    timings["total"] = data.time_s + time.perf_counter() - t0
    return SolveResult(table, winner, alphas, rel, solutions, data.level.copy(), data.level.copy(),
                       rule if isinstance(rule, str) else "given", timings, choice, kept_rule)


def solve(L: np.ndarray, I: np.ndarray, prior: Optional[Prior] = None, alpha=None, *,
          sigma: Optional[np.ndarray] = None, image_index: Optional[np.ndarray] = None,
          n_t: Optional[int] = None, n_s: Optional[int] = None,
          pairs: Sequence[str] = PAIRS, mean: Optional[np.ndarray] = None,
          mean_std: Optional[np.ndarray] = None, pair_rule: str = DEFAULT_PAIR_RULE,
          winner: Optional[Sequence[str]] = None) -> SolveResult:
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
        alpha: the smoothness prior's weight, or how it is chosen: ``"discrepancy"``
            (default, ``None``): one alpha for the three channels by the discrepancy
            principle (:func:`discrepancy_alpha`), at most :data:`DEFAULT_ALPHA`; a number,
            or three (per channel). ``"gcv"``: chosen per channel and pair by generalised
            cross-validation (:func:`gcv_curve`), and the pair with the lower GCV score wins.
        sigma: ``(M, 3)`` per-row noise std (default: :func:`row_sigma` of ``I``).
        image_index: ``(M,)`` image of each row (for the default ``sigma``).
        n_t, n_s: grid; default the prior's when it matches N, else sqrt(N).
        pairs: which pairs to solve with.
        mean, mean_std: ``(n_t, n_s, 3)`` 1/sr, a per-node Gaussian prior on the
            table (:meth:`mi_bivariate.basis_prior.BasisPrior.predict`), added as
            ``(1/M) sum ((f - mean) / mean_std)^2``.
        pair_rule: which pair is kept per channel (unless alpha is ``"gcv"``):
            ``"evidence"`` (default; the higher marginal likelihood of the image,
            :mod:`~mi_bivariate.solve.evidence`) or ``"residual"`` (the paper's: the lower
            data residual).
        winner: the pair to keep per channel, e.g. an earlier stage's ``result.winner``
            (overrides ``pair_rule``).

    Raises:
        InputError: shapes, NaN/inf, negative alpha, no observations, grid mismatch.
    """
    return solve_prepared(prepare_data_term(L, I, sigma, image_index), prior, alpha,
                          n_t=n_t, n_s=n_s, pairs=pairs, mean=mean, mean_std=mean_std, pair_rule=pair_rule,
                          winner=winner)


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
