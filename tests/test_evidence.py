"""The prior variant is kept by the evidence of the image (mi_bivariate.solve.evidence).

Checked against independent truths: the marginal likelihood written out in data space
(``M x M``, the Gaussian model integrated in closed form), the
pseudo-determinant against the eigenvalues, the NNLS solve's log det against LAPACK, and
``recover``'s two stages keeping the first stage's pair.
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import pytest

from mi_bivariate import solve
from mi_bivariate.basis_prior import BasisPrior
from mi_bivariate.errors import InputError
from mi_bivariate.prior import default_prior
from mi_bivariate.solve import nnls_gram, solve_stages
from mi_bivariate.solve.evidence import (
    channel_log_evidence,
    check_pair_rule,
    log_det_banded,
    log_det_spd,
    log_evidence,
    penalty_log_pdet,
)

N_T = N_S = 6
N = N_T * N_S


def _data_space_log_evidence(A: np.ndarray, y: np.ndarray, Q: np.ndarray, m0: Optional[np.ndarray] = None) -> float:
    """log p(y) of y ~ N(A f, 1/M), f ~ N(m0, Q^-1 / M) (m0 = 0 by default), written out in data space.

    y - A m0 ~ N(0, C / M) with C = I + A Q^-1 A^T: -1/2 log|C| - (M/2) r^T C^-1 r up to a constant of M.
    """
    m = len(y)
    r = y if m0 is None else y - A @ m0
    c = np.eye(m) + A @ np.linalg.solve(Q, A.T)
    sign, log_det = np.linalg.slogdet(c)
    assert sign > 0
    return -0.5 * log_det - 0.5 * m * (r @ np.linalg.solve(c, r))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_log_evidence_is_the_marginal_likelihood(seed):
    """Differences of log_evidence between priors equal those of the data-space formula."""
    rng = np.random.default_rng(seed)
    m = 60
    A = rng.standard_normal((m, N)) / np.sqrt(m)
    y = A @ rng.uniform(0.5, 2.0, N) + 0.05 * rng.standard_normal(m)
    prior = default_prior().resampled(N_T, N_S)
    values, truths = [], []
    for pair, lam in (("diffuse", 0.3), ("gloss", 0.3), ("gloss", 3.0)):
        p = prior.penalty_matrix(pair)
        d = rng.uniform(0.01, 0.1, N)  # a diagonal table prior: the precision is then of full rank
        q = lam * p + np.diag(d)
        g = A.T @ A
        f = np.linalg.solve(g + q, A.T @ y)
        phi = np.sum((y - A @ f) ** 2) + f @ q @ f
        sign, ld = np.linalg.slogdet(g + q)
        values.append(channel_log_evidence(phi, m, ld, lam, p, penalty_log_pdet(p), precision=d))
        truths.append(_data_space_log_evidence(A, y, q))
    np.testing.assert_allclose(np.diff(values), np.diff(truths), rtol=1e-9, atol=1e-8)
    assert abs(np.diff(truths)).max() > 0.1  # the priors differ in evidence


def test_improper_prior_is_the_limit_of_proper_ones():
    """The smoothness prior alone (constants unpenalised): the eps -> 0 limit of lambda P + eps J / N."""
    rng = np.random.default_rng(3)
    m = 50
    A = rng.standard_normal((m, N)) / np.sqrt(m)
    y = A @ rng.uniform(0.5, 2.0, N) + 0.05 * rng.standard_normal(m)
    prior = default_prior().resampled(N_T, N_S)
    g = A.T @ A
    got, limit = [], []
    eps = 1e-6  # small enough for the limit, large enough for C = I + A Q^-1 A^T to stay well conditioned
    for pair in ("diffuse", "gloss"):
        p, lam = prior.penalty_matrix(pair), 0.5
        f = np.linalg.solve(g + lam * p, A.T @ y)
        phi = np.sum((y - A @ f) ** 2) + lam * f @ p @ f
        got.append(channel_log_evidence(phi, m, np.linalg.slogdet(g + lam * p)[1], lam, p, penalty_log_pdet(p)))
        q = lam * p + eps * np.ones((N, N)) / N
        limit.append(_data_space_log_evidence(A, y, q))
    np.testing.assert_allclose(got[1] - got[0], limit[1] - limit[0], rtol=1e-4)
    assert abs(got[1] - got[0]) > 0.1


def test_penalty_log_pdet_against_eigenvalues():
    prior = default_prior().resampled(N_T, N_S)
    for pair in ("diffuse", "gloss"):
        p = prior.penalty_matrix(pair)
        w = np.linalg.eigvalsh(p)
        keep = w > 1e-10 * w.max()
        value, rank = penalty_log_pdet(p)
        assert rank == N - 1 == keep.sum()
        assert value == pytest.approx(np.sum(np.log(w[keep])), rel=1e-10)
    full = prior.penalty_matrix("gloss") + np.diag(np.linspace(0.1, 1.0, N))  # not a Laplacian
    value, rank = penalty_log_pdet(full)
    assert rank == N and value == pytest.approx(np.linalg.slogdet(full)[1], rel=1e-10)
    assert log_det_banded(full) == pytest.approx(np.linalg.slogdet(full)[1], rel=1e-12)
    assert penalty_log_pdet(np.zeros((4, 4))) == (0.0, 0)


def test_log_evidence_prefers_the_better_fit_and_the_tighter_prior():
    assert log_evidence(1.0, 0.0, 0.0, 100) > log_evidence(1.01, 0.0, 0.0, 100)
    assert log_evidence(1.0, 0.0, 5.0, 100) > log_evidence(1.0, 2.0, 5.0, 100)


def test_nnls_reports_the_systems_log_det():
    rng = np.random.default_rng(4)
    a = rng.standard_normal((40, 12))
    g = a.T @ a + 0.1 * np.eye(12)
    b = a.T @ rng.standard_normal(40)
    res = nnls_gram(g, b, passive=np.ones(12, bool))
    assert res.log_det == pytest.approx(np.linalg.slogdet(g)[1], rel=1e-12)
    assert np.any(res.x == 0)  # constraints ended active: the log det is the first, full solve's
    # From an empty start no passive-set solve covers every variable here: no log det to report.
    empty = nnls_gram(g, b)
    assert not np.all(empty.x > 0) and empty.log_det is None


def _problem(seed: int):
    rng = np.random.default_rng(seed)
    m = 400
    L = (rng.random((m, N)) ** 3 * (rng.random((m, N)) < 0.5))[:, :, None] * np.array([1.0, 0.8, 0.6])
    t = np.linspace(0, 1, N_T)[:, None, None]
    table = (0.3 + 20.0 * np.exp(-(t / 0.2) ** 2)) * np.ones((1, N_S, 3))
    I = np.einsum("mnc,nc->mc", L, table.reshape(N, 3)) * (1 + 0.02 * rng.standard_normal((m, 3)))
    return L.astype(np.float32), I


def test_solve_keeps_the_pair_with_the_higher_evidence_and_a_given_winner():
    L, I = _problem(5)
    prior = default_prior().resampled(N_T, N_S)
    data = solve.prepare_data_term(L, I)
    result = solve.solve_prepared(data, prior, 1e-2)
    assert result.pair_rule == "evidence"
    for k, w in enumerate(result.winner):
        ev = {p: s.log_evidence[k] for p, s in result.pairs.items()}
        assert np.all(np.isfinite(list(ev.values())))
        assert ev[w] == max(ev.values())
    forced = solve.solve_prepared(data, prior, 1e-2, winner=("gloss", "diffuse", "gloss"))
    assert forced.winner == ("gloss", "diffuse", "gloss") and forced.pair_rule == "given"
    np.testing.assert_array_equal(forced.table[:, :, 1], forced.pairs["diffuse"].table[:, :, 1])
    with pytest.raises(InputError, match="winner"):
        solve.solve_prepared(data, prior, 1e-2, winner=("gloss", "shiny", "gloss"))
    with pytest.raises(InputError, match="pair_rule"):
        solve.solve_prepared(data, prior, 1e-2, pair_rule="coin")


def _toy_basis() -> BasisPrior:
    """A basis prior learnt from 8 toy tables (a specular peak over a constant, random colours)."""
    rng = np.random.default_rng(7)
    t = np.linspace(0, 1, N_T)[:, None, None]
    tables = {f"m{i}": (rng.uniform(0.05, 0.5) + rng.uniform(1, 30) * np.exp(-(t / rng.uniform(0.1, 0.4)) ** 2))
              * rng.uniform(0.5, 1.0, 3) * np.ones((1, N_S, 1)) for i in range(8)}
    return BasisPrior.learn(tables, components=3)


def test_recover_stages_keep_the_first_stage_pairs():
    """Stage 2 (the basis prior) solves only the pairs stage 1 kept, and keeps them per channel."""
    L, I = _problem(6)
    prior = default_prior().resampled(N_T, N_S)
    basis = _toy_basis()
    data = solve.prepare_data_term(L, I)
    first = solve.solve_prepared(data, prior)
    both = solve_stages(data, prior, None, basis)
    assert both.winner == first.winner
    assert both.pair_rule == first.pair_rule == "evidence"
    assert both.alpha_rule == first.alpha_rule == "discrepancy"
    np.testing.assert_array_equal(both.alphas, first.alphas)
    assert set(both.pairs) == set(first.winner)
    assert not np.array_equal(both.table, first.table)  # the basis prior did act


def test_cli_offers_the_pair_rules(capsys):
    from mi_bivariate.cli import build_parser, main

    parser = build_parser()
    args = parser.parse_args(["recover", "img.exr", "--probe", "p.exr", "--pair-rule", "residual"])
    assert args.pair_rule == "residual"
    assert parser.parse_args(["recover", "img.exr", "--probe", "p.exr"]).pair_rule == solve.DEFAULT_PAIR_RULE
    action = next(a for sub in parser._subparsers._group_actions for name, p in sub.choices.items()
                  if name == "recover" for a in p._actions if a.dest == "pair_rule")
    assert tuple(action.choices) == solve.PAIR_RULES
    with pytest.raises(SystemExit) as stop:
        main(["recover", "img.exr", "--probe", "p.exr", "--pair-rule", "coin"])
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("mi-bivariate: error:") and "pair-rule" in err[0]


def test_evidence_across_prior_weights_is_the_limit_of_proper_ones():
    """One pair at two weights (``lambda`` 0.5 and 3): the difference of the evidences (through the
    ``rank log lambda`` of the prior's determinant) is the data-space one of the proper limit."""
    rng = np.random.default_rng(4)
    m = 50
    A = rng.standard_normal((m, N)) / np.sqrt(m)
    y = A @ rng.uniform(0.5, 2.0, N) + 0.05 * rng.standard_normal(m)
    p = default_prior().resampled(N_T, N_S).penalty_matrix("gloss")
    g = A.T @ A
    got, limit = [], []
    for lam in (0.5, 3.0):
        f = np.linalg.solve(g + lam * p, A.T @ y)
        phi = np.sum((y - A @ f) ** 2) + lam * f @ p @ f
        got.append(channel_log_evidence(phi, m, np.linalg.slogdet(g + lam * p)[1], lam, p, penalty_log_pdet(p)))
        limit.append(_data_space_log_evidence(A, y, lam * p + 1e-6 * np.ones((N, N)) / N))
    np.testing.assert_allclose(got[1] - got[0], limit[1] - limit[0], rtol=1e-4)
    assert abs(got[1] - got[0]) > 0.1


def _weighted(data, k):
    """``(A, y)`` of channel ``k`` as the solve normalises them: ``L / (sigma sqrt(M))``, ``I / (sigma sqrt(M))``."""
    m = data.n_rows
    w = 1.0 / (data.sigma[:, k] * np.sqrt(m))
    return data.lighting[:, :, k].astype(np.float64) * w[:, None], data.observations[:, k].astype(np.float64) * w


@pytest.mark.parametrize("table_prior", [False, True, "mean"])
def test_solve_reports_the_data_space_evidence(table_prior):
    """The evidence ``solve`` reports (its objective, log det and prior pdet together) against the marginal
    likelihood written out in data space, for a problem whose constraints are inactive (the MAP estimate
    is then the Gaussian posterior mean, where the formula is exact). Without a table prior: the smoothness
    prior's proper limit (as above); with a zero-mean table prior (precision ``1 / (M std^2)``, of full
    rank): the proper Gaussian itself, whose evidence is the data-space one with no constant left out
    (``det C = det(G + Q) / det Q`` and ``y^T C^-1 y = Phi``); its zero mean starts the solve from an
    empty passive set."""
    L, I = _problem(8)
    prior = default_prior().resampled(N_T, N_S)
    data = solve.prepare_data_term(L, I)
    m, alpha = data.n_rows, 1e-2
    kwargs = {}
    if table_prior:
        std = np.full((N_T, N_S, 3), 3.0) * data.level  # weak beside the data: no node is pulled to zero
        # a zero mean, or (the basis prior's case) a mean of its own: the Gaussian prior is then about
        # Q^-1 D mean, and Phi holds a constant beside its exponent that depends on the pair
        mean = np.zeros((N_T, N_S, 3)) if table_prior is True else \
            np.random.default_rng(4).uniform(0.5, 1.5, (N_T, N_S, 3)) * data.level
        kwargs = dict(mean=mean, mean_std=std)
    result = solve.solve_prepared(data, prior, alpha, **kwargs)
    for k in range(3):
        A, y = _weighted(data, k)
        truth = {}
        for pair, sol in result.pairs.items():
            assert np.all(sol.table[:, :, k] > 0)  # no active constraint: the formula is exact
            q = alpha / (N * data.level[k] ** 2) * prior.penalty_matrix(pair)
            m0 = None
            if table_prior:
                d = 1.0 / (m * kwargs["mean_std"][:, :, k].ravel() ** 2)
                q = q + np.diag(d)
                m0 = np.linalg.solve(q, d * kwargs["mean"][:, :, k].ravel())
            else:
                q = q + 1e-6 * np.ones((N, N)) / N
            truth[pair] = _data_space_log_evidence(A, y, q, m0)
        got = result.pairs["gloss"].log_evidence[k] - result.pairs["diffuse"].log_evidence[k]
        expected = truth["gloss"] - truth["diffuse"]
        assert got == pytest.approx(expected, rel=1e-4, abs=1e-6 * m)
        assert abs(expected) > 0.1  # the pairs differ in evidence
        if table_prior:  # a proper prior: no constant left out, the values themselves agree
            for pair, sol in result.pairs.items():
                assert sol.log_evidence[k] == pytest.approx(truth[pair], rel=1e-6)


def test_log_dets_against_slogdet_and_a_singular_precision_against_its_eigenvalues():
    """``log_det_spd`` and ``log_det_banded`` (whose banded Cholesky must refuse a matrix that is not
    positive definite and hand it to the dense route) against ``slogdet``; ``penalty_log_pdet`` of a
    rank-deficient precision that is not a graph Laplacian against its non-zero eigenvalues."""
    from mi_bivariate.solve.evidence import log_det_spd

    rng = np.random.default_rng(9)
    a = rng.standard_normal((40, 12))
    spd = a.T @ a + 0.1 * np.eye(12)
    assert log_det_spd(spd) == pytest.approx(np.linalg.slogdet(spd)[1], rel=1e-12)
    # Tridiagonal, symmetric, two negative eigenvalues: det > 0 but not positive definite.
    indefinite = np.diag(np.r_[1.0, -2.0, -3.0, 2.0, 1.5, 1.0]) + 0.1 * (np.eye(6, k=1) + np.eye(6, k=-1))
    sign, value = np.linalg.slogdet(indefinite)
    assert sign > 0 and np.linalg.eigvalsh(indefinite).min() < 0
    assert log_det_banded(indefinite) == pytest.approx(value, rel=1e-12)
    assert log_det_banded(indefinite, band=1) == pytest.approx(value, rel=1e-12)
    b = rng.standard_normal((N - 3, N))
    p = b.T @ b  # PSD of rank N - 3, rows not summing to zero
    w = np.linalg.eigvalsh(p)
    keep = w > 1e-10 * w.max()
    value, rank = penalty_log_pdet(p)
    assert rank == N - 3 == keep.sum()
    assert value == pytest.approx(np.sum(np.log(w[keep])), rel=1e-10)


@pytest.mark.parametrize("alpha", [None, "gcv"])
def test_second_stage_is_the_stacked_nnls_with_the_basis_prediction(alpha):
    """Stage 2 of ``solve_stages``: the basis prior's prediction from stage 1's table, resolution and
    posterior spread (in that order) joins the objective as ``(1/M) ||(f - mean) / std||^2`` at stage 1's
    alphas (with GCV, choosing again with the basis prior would move them); every channel's table
    against ``scipy.optimize.nnls`` on the stacked least-squares problem."""
    import scipy.optimize as sopt

    L, I = _problem(6)
    prior = default_prior().resampled(N_T, N_S)
    basis = _toy_basis()
    data = solve.prepare_data_term(L, I)
    first = solve.solve_prepared(data, prior, alpha)
    both = solve_stages(data, prior, alpha, basis)
    np.testing.assert_array_equal(both.alphas, first.alphas)
    mean, std = basis.predict(first.table, first.resolution, first.posterior_std)
    m = data.n_rows
    for k, pair in enumerate(both.winner):
        A, y = _weighted(data, k)
        lam = both.alphas[k] / (N * data.level[k] ** 2)
        w = 1.0 / (std[:, :, k].ravel() * np.sqrt(m))
        stacked = np.vstack([A, np.sqrt(lam) * prior.regulariser(pair).toarray(), np.diag(w)])
        rhs = np.concatenate([y, np.zeros(stacked.shape[0] - len(y) - N), mean[:, :, k].ravel() * w])
        expected, _ = sopt.nnls(stacked, rhs, maxiter=100 * N)
        np.testing.assert_allclose(both.table[:, :, k].ravel(), expected, rtol=1e-5, atol=1e-6 * expected.max())


def test_solve_prepared_refuses_each_bad_argument():
    """Each check of ``solve_prepared``'s arguments on its own, an InputError naming the argument: a winner
    for two channels, no pair, a table-prior mean without its std (or the std alone), a std of 0, an unknown
    confidence map, and ``alpha_sweep``'s truth on another grid."""
    L, I = _problem(5)
    prior = default_prior().resampled(N_T, N_S)
    data = solve.prepare_data_term(L, I)
    mean = np.full((N_T, N_S, 3), 1.0)
    for kwargs, name in ((dict(winner=("gloss", "diffuse")), "winner"), (dict(pairs=()), "pairs"),
                         (dict(mean=mean), "mean"), (dict(mean_std=mean), "mean"),
                         (dict(mean=mean, mean_std=np.where(np.arange(N) == 7, 0.0, 1.0).reshape(N_T, N_S, 1)
                               * mean), "std > 0"),
                         (dict(maps=("resolution", "sharpness")), "maps")):
        with pytest.raises(InputError, match=name):
            solve.solve_prepared(data, prior, 1e-2, **kwargs)
    with pytest.raises(InputError, match="truth"):
        solve.alpha_sweep(L, I, [1e-2], prior, truth=np.zeros((N_T, N_S + 1, 3)))


def test_stages_take_the_pair_rule_and_report_the_first_stage_alpha_choice():
    """``solve_stages(pair_rule="residual")`` keeps per channel the pair with the lower data term of stage 1
    (here "diffuse" where the evidence keeps "gloss"), and its result reports stage 1's discrepancy choice."""
    L, I = _problem(6)
    prior = default_prior().resampled(N_T, N_S)
    data = solve.prepare_data_term(L, I)
    first = solve.solve_prepared(data, prior)
    both = solve_stages(data, prior, None, _toy_basis(), pair_rule="residual")
    residual = tuple(min(first.pairs, key=lambda p: first.pairs[p].data_term[k]) for k in range(3))
    assert both.winner == residual != first.winner and both.pair_rule == "residual"
    assert both.alpha_choice is not None and both.alpha_choice.alpha == first.alpha_choice.alpha
    np.testing.assert_array_equal(both.alpha_choice.data_terms, first.alpha_choice.data_terms)


def test_evidence_without_a_prior_is_the_fit_and_the_data_terms_determinant():
    """alpha = 0 and no table prior (a flat prior): ``log p(y) = -(M/2) Phi - 1/2 log det G`` per channel, with
    ``Phi`` the data term and ``G = A^T A`` written out; finite, with no warning from ``log(0)``."""
    import warnings

    L, I = _problem(9)
    prior = default_prior().resampled(N_T, N_S)
    data = solve.prepare_data_term(L, I)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        result = solve.solve_prepared(data, prior, 0.0)
    for k in range(3):
        A, y = _weighted(data, k)
        for sol in result.pairs.values():
            f = sol.table[:, :, k].ravel().astype(np.float64)
            phi = np.sum((y - A @ f) ** 2)
            expected = -0.5 * data.n_rows * phi - 0.5 * np.linalg.slogdet(A.T @ A)[1]
            assert sol.log_evidence[k] == pytest.approx(expected, rel=1e-6)


def test_evidence_helpers_at_the_edges_of_their_inputs():
    """Against ``slogdet``: a symmetric matrix of negative determinant has no log det (``-inf``, not
    ``log |det|``); a diagonal matrix (bandwidth 0: the table prior alone at alpha 0) is read from its banded
    factor's diagonal; a pair rule that is no string is an InputError, never a traceback."""
    negative = np.diag([2.0, -1.0, 3.0]) + 0.1 * (np.eye(3, k=1) + np.eye(3, k=-1))
    assert np.linalg.slogdet(negative)[0] < 0
    assert log_det_spd(negative) == -np.inf
    d = np.random.default_rng(10).uniform(0.1, 5.0, 9)
    for band in (None, 0):
        assert log_det_banded(np.diag(d), band) == pytest.approx(np.linalg.slogdet(np.diag(d))[1], rel=1e-12)
    for bad in (None, 1, ("evidence",), np.array(["evidence", "residual"])):
        with pytest.raises(InputError, match="pair_rule"):
            check_pair_rule(bad)


def _grid_laplacian(n_t: int, n_s: int, weights: np.ndarray) -> np.ndarray:
    """``(N, N)`` ``D^T diag(weights) D`` of the grid's first differences (``D``: every edge, s then t)."""
    ds, dt = [], []
    for it in range(n_t):
        for i_s in range(n_s):
            if i_s + 1 < n_s:
                ds.append((it * n_s + i_s, it * n_s + i_s + 1))
            if it + 1 < n_t:
                dt.append((it * n_s + i_s, (it + 1) * n_s + i_s))
    edges = ds + dt
    d = np.zeros((len(edges), n_t * n_s))
    for row, (a, b) in enumerate(edges):
        d[row, a], d[row, b] = -1.0, 1.0
    return d.T @ (weights[: len(edges), None] * d)


def test_penalty_log_pdet_of_a_laplacian_in_two_pieces():
    """A weighted grid Laplacian whose edges between the two halves of the grid weigh 0 (rows summing to 0,
    but two null vectors): the matrix-tree shortcut ``pdet P = N det P'`` holds for a connected graph only.
    It was taken anyway, ``P'`` being singular by one round-off pivot, and gave rank ``N - 1`` and a log
    pseudo-determinant tens too low; the eigenvalues give rank ``N - 2`` and the right value. On the connected
    grid the shortcut's answer is the eigenvalues'."""
    rng = np.random.default_rng(11)
    n_t, n_s = 6, 5
    n = n_t * n_s
    weights = rng.uniform(0.5, 2.0, 2 * n)
    connected = _grid_laplacian(n_t, n_s, weights)
    cut = weights.copy()
    edges_t0 = (n_s - 1) * n_t  # the s edges come first; t edge of node (it, is) follows
    cut[edges_t0 + (n_t // 2 - 1) * n_s: edges_t0 + (n_t // 2) * n_s] = 0.0  # rows 2 -> 3: the grid in two
    pieces = _grid_laplacian(n_t, n_s, cut)
    for p, rank in ((connected, n - 1), (pieces, n - 2)):
        w = np.linalg.eigvalsh(p)
        keep = w > 1e-10 * w.max()
        assert keep.sum() == rank
        assert penalty_log_pdet(p) == (pytest.approx(np.sum(np.log(w[keep])), rel=1e-10), rank)


def test_log_det_banded_of_positive_definite_banded_matrices_against_slogdet():
    """``log_det_banded`` reads the matrix into LAPACK's upper banded storage (``ab[b - d, j] = x[j - d, j]``):
    on banded matrices that stay positive definite however their diagonals are shifted (diagonally dominant),
    a misplaced diagonal would still factorise, so only ``slogdet`` tells; bands of 1 to 12, and a band given
    wider than the matrix's."""
    rng = np.random.default_rng(12)
    for n, band, given in ((30, 1, None), (30, 5, None), (40, 12, None), (25, 3, 8)):
        z = rng.uniform(-1.0, 1.0, (n, n)) * (np.abs(np.subtract.outer(np.arange(n), np.arange(n))) <= band)
        q = 0.5 * (z + z.T)
        q += np.diag(np.abs(q).sum(axis=1) + rng.uniform(0.1, 1.0, n))
        assert log_det_banded(q, given) == pytest.approx(np.linalg.slogdet(q)[1], rel=1e-12)
