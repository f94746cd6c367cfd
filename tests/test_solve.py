"""The constrained regularised solve (Eq. 6) against independent solvers and closed forms."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import scipy.optimize as sopt

from mi_bivariate.errors import InputError
from mi_bivariate.prior import Prior
from mi_bivariate.solve import discrepancy as disc
from mi_bivariate.solve import (
    DEFAULT_ALPHA,
    DISCREPANCY_ALPHAS,
    DISCREPANCY_TARGET,
    KKT_TOLERANCE,
    alpha_sweep,
    check_alpha,
    discrepancy_alpha,
    gcv_curve,
    kkt_violation,
    nnls_gram,
    prepare_data_term,
    row_sigma,
    solve,
    solve_prepared,
)
from mi_bivariate.solve.common import cholesky, inverse_diagonals, spd_inverse

N_T, N_S = 6, 5
N = N_T * N_S


def _problem(kind: str, seed: int, m: int = 120, n: int = 40):
    """``(A, a)`` for ``min ||A x - a||, x >= 0`` of a given character."""
    rng = np.random.default_rng(seed)
    a_mat = rng.standard_normal((m, n))
    if kind == "ill":  # column scales over 5 decades: cond ~ 1e5
        a_mat *= np.logspace(0, -5, n)
    elif kind == "collinear":  # nearly collinear columns
        a_mat = a_mat[:, :1] + 1e-3 * a_mat
    truth = np.maximum(rng.standard_normal(n), 0.0)
    rhs = a_mat @ truth + 0.1 * rng.standard_normal(m)
    if kind == "active":  # most constraints active at the solution
        # The unconstrained optimum is negative except on 5 coordinates.
        coeffs = -np.abs(rng.standard_normal(n))
        coeffs[:5] = 3.0
        rhs = a_mat @ coeffs + 0.1 * rng.standard_normal(m)
    return a_mat, rhs


@pytest.mark.parametrize("start", ["empty", "full"])  # full: the one-factor (Schur) route
@pytest.mark.parametrize("kind", ["well", "ill", "collinear", "active"])
def test_nnls_gram_matches_scipy_nnls(kind, start):
    for seed in range(4):
        a_mat, rhs = _problem(kind, seed)
        expected, _ = sopt.nnls(a_mat, rhs, maxiter=100 * a_mat.shape[1])
        g, b = a_mat.T @ a_mat, a_mat.T @ rhs
        res = nnls_gram(g, b, passive=np.full(b.size, start == "full"))
        assert res.method == "bpp"
        if start == "full":  # the factor handed to the confidence is the whole G's
            assert res.factor is not None
            c, lower = res.factor
            u = np.tril(c).T if lower else np.triu(c)
            np.testing.assert_allclose(u.T @ u, g, rtol=0, atol=1e-12 * np.abs(g).max())
        assert res.kkt_violation < 1e-12
        assert np.all(res.x >= 0)
        # Both exact: they differ by the conditioning times round-off only.
        tol = 1e-9 if kind == "well" else 1e-6
        np.testing.assert_allclose(res.x, expected, rtol=0, atol=tol * max(1.0, np.abs(expected).max()))
        if kind == "active":
            assert np.count_nonzero(res.x) < a_mat.shape[1] // 2


def test_kkt_check_catches_a_wrong_answer_and_falls_back():
    a_mat, rhs = _problem("active", 7)
    G, b = a_mat.T @ a_mat, a_mat.T @ rhs
    exact, _ = sopt.nnls(a_mat, rhs)
    assert kkt_violation(G, b, exact) < 1e-12
    wrong = exact * 1.01
    assert kkt_violation(G, b, wrong) > 1e-4
    off_support = exact.copy()
    off_support[np.flatnonzero(exact == 0)[0]] = 1e-3 * exact.max()
    assert kkt_violation(G, b, off_support) > 1e-6
    negative = exact.copy()
    negative[np.flatnonzero(exact)[0]] *= -1
    assert kkt_violation(G, b, negative) > 1e-4
    # Pivoting stopped after one solve cannot satisfy KKT here: the fallback must run and be exact.
    res = nnls_gram(G, b, passive=np.ones(b.size, bool), max_iter=1)
    assert res.method == "bpp+nnls-fallback"
    assert res.kkt_violation < KKT_TOLERANCE
    np.testing.assert_allclose(res.x, exact, atol=1e-9 * exact.max())


def _lighting(m: int, seed: int) -> np.ndarray:
    """A non-negative, full-rank ``(m, N, 3)`` float32 lighting matrix with coloured light."""
    rng = np.random.default_rng(seed)
    base = rng.random((m, N)) ** 3
    return (base[:, :, None] * np.array([1.0, 0.7, 0.4]) * rng.uniform(0.5, 2.0, (m, 1, 3))).astype(np.float32)


def _truth(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    table = rng.random((N_T, N_S, 3))
    table[rng.random((N_T, N_S, 3)) < 0.3] = 0.0  # zeros: constraints active at the truth
    return table


def _prior() -> Prior:
    """Two different, non-uniform pairs on the test grid."""
    rng = np.random.default_rng(3)
    return Prior({p: (rng.uniform(0.2, 5.0, (N_T, N_S)), rng.uniform(0.2, 5.0, (N_T, N_S)))
                  for p in ("diffuse", "gloss")})


def test_solve_matches_scipy_nnls_on_the_stacked_system():
    """The documented objective, written out as one stacked least-squares problem."""
    L = _lighting(150, 1)
    I = np.einsum("mnk,nk->mk", L.astype(np.float64), _truth(2).reshape(N, 3))
    I *= 1 + 0.05 * np.random.default_rng(4).standard_normal(I.shape)
    prior, alpha = _prior(), 0.3
    result = solve(L, I, prior, alpha, n_t=N_T, n_s=N_S)
    sigma = row_sigma(I)
    m = L.shape[0]
    ones = np.ones(N)
    for pair, sol in result.pairs.items():
        for k in range(3):
            l_k = L[:, :, k].astype(np.float64)
            w = 1.0 / (sigma[:, k] * np.sqrt(m))
            g, b = (l_k * w[:, None]).T @ (l_k * w[:, None]), (l_k * w[:, None]).T @ (I[:, k] * w)
            level = (ones @ b) / (ones @ g @ ones)
            reg = np.sqrt(alpha / (N * level**2)) * prior.regulariser(pair).toarray()
            stacked = np.vstack([l_k * w[:, None], reg])
            rhs = np.concatenate([I[:, k] * w, np.zeros(reg.shape[0])])
            expected, _ = sopt.nnls(stacked, rhs, maxiter=100 * N)
            np.testing.assert_allclose(sol.table[:, :, k].ravel(), expected, rtol=1e-5, atol=1e-6 * expected.max())
            resid = I[:, k] - l_k @ expected
            assert sol.relative_residual[k] == pytest.approx(np.linalg.norm(resid) / np.linalg.norm(I[:, k]), rel=1e-4)
            assert sol.data_term[k] == pytest.approx(np.sum((resid * w) ** 2), rel=1e-4)
            assert sol.prior_term[k] == pytest.approx(
                np.sum((prior.regulariser(pair) @ expected) ** 2) / (N * level**2), rel=1e-4)
        assert np.all(sol.kkt_violation < 1e-12)
        assert np.all((sol.resolution >= 0) & (sol.resolution <= 1))
    # The kept table is, per channel, the pair with the higher evidence (the default rule) ...
    assert result.pair_rule == "evidence"
    for k, w in enumerate(result.winner):
        other = "gloss" if w == "diffuse" else "diffuse"
        assert result.pairs[w].log_evidence[k] >= result.pairs[other].log_evidence[k]
        np.testing.assert_array_equal(result.table[:, :, k], result.pairs[w].table[:, :, k])
    # ... or, asked for, the pair with the lower data term (the paper's rule), same tables.
    paper = solve(L, I, prior, alpha, n_t=N_T, n_s=N_S, pair_rule="residual")
    assert paper.pair_rule == "residual" and np.all(np.isnan(paper.pairs["gloss"].log_evidence))
    for k, w in enumerate(paper.winner):
        other = "gloss" if w == "diffuse" else "diffuse"
        assert paper.pairs[w].data_term[k] <= paper.pairs[other].data_term[k]
        np.testing.assert_array_equal(paper.table[:, :, k], result.pairs[w].table[:, :, k])


def test_images_combine_by_information_not_brightness():
    """Two images stacked: scaling one image and its probe by 50 changes nothing."""
    L = _lighting(160, 21)
    truth = _truth(22)
    I = np.einsum("mnk,nk->mk", L.astype(np.float64), truth.reshape(N, 3))
    I *= 1 + 0.03 * np.random.default_rng(23).standard_normal(I.shape)
    index = np.repeat([0, 1], 80)
    base = solve(L, I, _prior(), 0.1, image_index=index, n_t=N_T, n_s=N_S)
    scale = np.where(index == 1, 50.0, 1.0)
    scaled = solve(L * scale[:, None, None], I * scale[:, None], _prior(), 0.1, image_index=index,
                   n_t=N_T, n_s=N_S)
    np.testing.assert_allclose(scaled.table, base.table, rtol=1e-4, atol=1e-6 * base.table.max())
    # Without per-image weights (one sigma scale for all rows) the bright image dominates.
    unweighted = solve(L * scale[:, None, None], I * scale[:, None], _prior(), 0.1,
                       sigma=np.ones_like(I), n_t=N_T, n_s=N_S)
    assert np.abs(unweighted.table - base.table).max() > 1e-3 * base.table.max()


def test_gcv_trace_and_choice():
    """Hutchinson's trace against the exact one; GCV's alpha near the error-minimising alpha."""
    rng = np.random.default_rng(31)
    L = _lighting(300, 32)
    truth = _truth(33)
    clean = np.einsum("mnk,nk->mk", L.astype(np.float64), truth.reshape(N, 3))
    I = clean * (1 + 0.05 * rng.standard_normal(clean.shape))
    sigma = 0.05 * np.abs(clean) + 1e-12
    data = prepare_data_term(L, I, sigma)
    penalty = _prior().penalty_matrix("diffuse")
    curve = gcv_curve(data, penalty, 1, probes=256)
    for alpha, dof in zip(curve.alphas, curve.dof):
        lam = alpha / (N * data.level[1] ** 2)
        exact = np.trace(np.linalg.solve(data.gram[1] + lam * penalty, data.gram[1]))
        assert dof == pytest.approx(exact, rel=0.1, abs=0.5)
    errors = []
    for alpha in curve.alphas:
        lam = alpha / (N * data.level[1] ** 2)
        f = np.linalg.solve(data.gram[1] + lam * penalty, data.rhs[1])
        errors.append(np.linalg.norm(f - truth[:, :, 1].ravel()))
    lam = curve.alpha / (N * data.level[1] ** 2)
    chosen = np.linalg.norm(np.linalg.solve(data.gram[1] + lam * penalty, data.rhs[1]) - truth[:, :, 1].ravel())
    assert chosen <= 1.5 * min(errors)
    assert chosen < 0.5 * errors[-1] and chosen < 0.5 * max(errors)


def _unconstrained_data_term(data, penalty, k, alpha):
    lam = alpha / (N * data.level[k] ** 2)
    f = np.linalg.solve(data.gram[k] + lam * penalty, data.rhs[k])
    return float(data.yy[k] - 2 * f @ data.rhs[k] + f @ data.gram[k] @ f)


def _noisy_problem(noise: float, seed: int = 41):
    rng = np.random.default_rng(seed)
    L = _lighting(300, seed)
    clean = np.einsum("mnk,nk->mk", L.astype(np.float64), _truth(seed + 1).reshape(N, 3))
    return L, clean * (1 + noise * rng.standard_normal(clean.shape)), noise * np.abs(clean) + 1e-12


@pytest.mark.parametrize("start", [1e-2, 1e3])
def test_discrepancy_alpha_against_a_dense_scan(start):
    """The walk (up or down from ``start``) and its refinement find where a dense scan of direct solves
    crosses the target; a wide grid, so that the data term is steep in part of it."""
    L, I, sigma = _noisy_problem(0.05)
    data = prepare_data_term(L, I, sigma)
    penalty = _prior().penalty_matrix("diffuse")
    grid = 10.0 ** np.arange(-2.0, 3.01, 0.5)
    dense = np.logspace(-2, 3, 251)
    for k in range(3):
        rho = np.array([_unconstrained_data_term(data, penalty, k, a) for a in dense])
        assert np.all(np.diff(rho) >= -1e-9 * rho[1:])  # the data term grows with alpha
        slope = np.gradient(np.log(rho), np.log(dense))
        assert slope[50] > 0.25  # steep there: alpha is pinned by the target
        for i in range(10, 241, 7):  # crossings inside the range
            target = rho[i] * 1.0001
            choice = discrepancy_alpha(data, penalty, (k,), target=target, alphas=grid, start=start)
            assert choice.bounded == ""
            # 1%: the regula falsi step matters (linear interpolation alone misses by up to 3% here)
            assert _unconstrained_data_term(data, penalty, k, choice.alpha) == pytest.approx(target, rel=0.01)
            if slope[i] > 0.1:  # alpha itself is pinned where the data term is not flat
                assert choice.alpha == pytest.approx(dense[i], rel=0.01 / slope[i] + 0.02)
        if k == 2:  # one alpha for all channels: the mean of their data terms meets the target
            target = np.mean([_unconstrained_data_term(data, penalty, c, 1.0) for c in range(3)])
            choice = discrepancy_alpha(data, penalty, target=target, alphas=grid, start=start)
            assert np.mean([_unconstrained_data_term(data, penalty, c, choice.alpha) for c in range(3)]) == \
                pytest.approx(target, rel=0.02)
            assert choice.alpha == pytest.approx(1.0, rel=0.1)
        low = discrepancy_alpha(data, penalty, (k,), target=0.5 * rho[0], alphas=grid, start=start)
        assert low.bounded == "low" and low.alpha == pytest.approx(1e-2)
        high = discrepancy_alpha(data, penalty, (k,), target=2 * rho[-1], alphas=grid, start=start)
        assert high.bounded == "high" and high.alpha == pytest.approx(1e3)
    # The package's own range: from 1e-4 up to the learnt default alpha, which bounds it.
    assert DISCREPANCY_ALPHAS[0] == pytest.approx(1e-4) and DISCREPANCY_ALPHAS[-1] == DEFAULT_ALPHA


def test_discrepancy_is_the_default_and_alpha_grows_with_the_noise():
    assert check_alpha(None) == "discrepancy"
    chosen = []
    for noise in (0.01, 0.05, 0.2):
        L, I, _ = _noisy_problem(noise)
        # The same model-error sigma for all three: more noise leaves more residual, so a weaker prior
        # would over-fit it; camera noise given in sigma instead lets alpha grow (below).
        result = solve(L, I, _prior(), n_t=N_T, n_s=N_S, sigma=0.05 * np.abs(I) + 1e-12)
        assert result.alpha_rule == "discrepancy" and np.all(result.alphas == result.alpha_choice.alpha)
        chosen.append(result.alphas)
    assert np.all(chosen[0] >= chosen[1]) and np.all(chosen[1] >= chosen[2])
    L, I, _ = _noisy_problem(0.05)
    sigmas = [row_sigma(I, noise=[(a, 0.0)]) for a in (0.0, 1e-3 * np.mean(I), 1e-2 * np.mean(I))]
    alphas = [solve(L, I, _prior(), n_t=N_T, n_s=N_S, sigma=s).alphas for s in sigmas]
    assert np.all(alphas[0] <= alphas[1]) and np.all(alphas[1] <= alphas[2]) and np.any(alphas[0] < alphas[2])
    # Scale-free: a brighter image and probe choose the same alphas.
    base = solve(L, I, _prior(), n_t=N_T, n_s=N_S)
    np.testing.assert_allclose(solve(L * 10, I * 10, _prior(), n_t=N_T, n_s=N_S).alphas, base.alphas, rtol=1e-6)
    assert DISCREPANCY_TARGET > 0


def test_alpha_zero_noiseless_recovers_the_truth():
    L = _lighting(200, 5)
    truth = _truth(6)
    I = np.einsum("mnk,nk->mk", L.astype(np.float64), truth.reshape(N, 3))
    result = solve(L, I, _prior(), alpha=0.0, n_t=N_T, n_s=N_S)
    np.testing.assert_allclose(result.table, truth, rtol=0, atol=1e-6)  # float32 table
    for sol in result.pairs.values():
        np.testing.assert_allclose(sol.table, truth, atol=1e-6)
        assert np.all(sol.relative_residual < 1e-6)


def test_constant_truth_converges_at_the_lambertian_start():
    L = _lighting(100, 8)
    albedo = np.array([0.3, 0.2, 0.05])  # 1/sr
    I = L.astype(np.float64).sum(axis=1) * albedo
    result = solve(L, I, _prior(), alpha=1.0, n_t=N_T, n_s=N_S)
    np.testing.assert_allclose(result.lambertian, albedo, rtol=1e-12)
    np.testing.assert_allclose(result.table, np.broadcast_to(albedo, result.table.shape), rtol=1e-6)
    for sol in result.pairs.values():
        assert np.all(sol.iterations == 1)  # the start's passive set is already optimal
        assert np.all(sol.prior_term < 1e-20)


def test_scale_invariance():
    L = _lighting(150, 9)
    I = np.einsum("mnk,nk->mk", L.astype(np.float64), _truth(10).reshape(N, 3))
    I *= 1 + 0.05 * np.random.default_rng(11).standard_normal(I.shape)
    prior = _prior()
    base = solve(L, I, prior, 0.5, n_t=N_T, n_s=N_S)
    brighter_probe = solve(L * 10, I * 10, prior, 0.5, n_t=N_T, n_s=N_S)  # same material, brighter light
    np.testing.assert_allclose(brighter_probe.table, base.table, rtol=1e-5, atol=1e-7)
    same_probe_lit_10x = solve(L * 10, I, prior, 0.5, n_t=N_T, n_s=N_S)
    np.testing.assert_allclose(same_probe_lit_10x.table, base.table / 10, rtol=1e-5, atol=1e-8)
    brighter_material = solve(L, I * 10, prior, 0.5, n_t=N_T, n_s=N_S)
    np.testing.assert_allclose(brighter_material.table, base.table * 10, rtol=1e-5, atol=1e-6)
    assert brighter_material.winner == base.winner


def test_prior_grid_is_resampled_and_sweep_reuses_the_data():
    L = _lighting(120, 12)
    truth = _truth(13)
    I = np.einsum("mnk,nk->mk", L.astype(np.float64), truth.reshape(N, 3))
    points = alpha_sweep(L, I, [0.0, 1e-2, 10.0], Prior.uniform(32, 32), truth=truth, n_t=N_T, n_s=N_S)
    errors = [p.table_error.max() for p in points]
    assert errors[0] < 1e-6 and errors[0] < errors[1] < errors[2]
    data = prepare_data_term(L, I)
    assert data.gram.shape == (3, N, N) and data.scale.shape == (3,)


def test_input_errors():
    L = _lighting(20, 0)
    I = np.ones((20, 3))
    prior = Prior.uniform(N_T, N_S)
    with pytest.raises(InputError, match="rows"):
        solve(L, I[:10], prior)
    with pytest.raises(InputError, match="shape"):
        solve(L[:, :, :2], I, prior)
    bad = L.copy()
    bad[3, 4, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        solve(bad, I, prior)
    bad_i = I.copy()
    bad_i[0, 0] = np.inf
    with pytest.raises(InputError, match="NaN"):
        solve(L, bad_i, prior)
    with pytest.raises(InputError, match="alpha"):
        solve(L, I, prior, alpha=-1.0)
    with pytest.raises(InputError, match="alpha"):
        solve(L, I, prior, alpha="morozov")
    with pytest.raises(InputError, match="M = 0"):
        solve(L[:0], I[:0], prior)
    with pytest.raises(InputError, match="grid"):
        solve(L, I, prior, n_t=4, n_s=4)
    with pytest.raises(InputError, match="all zero"):
        solve(np.zeros_like(L), I, prior)


def test_discrepancy_search_brackets_the_target_with_few_evaluations(monkeypatch):
    """On any increasing data-term curve the grid search returns the bracketing pair's refinement,
    the bounds at the ends, and costs 1 evaluation when the default meets the target, 2 at the floor."""
    from mi_bivariate.solve import discrepancy as disc

    rng = np.random.default_rng(0)
    logs = np.log10(DISCREPANCY_ALPHAS)
    for _ in range(300):
        values = np.sort(rng.uniform(0.0, 50.0, len(logs)))
        target = float(rng.uniform(0.0, 55.0))
        calls = []

        def fake(data, entries, channels, alpha, extra, values=values, calls=calls):
            calls.append(alpha)
            return float(np.interp(np.log10(alpha), logs, values)), [("factor at", alpha)] * 3

        monkeypatch.setattr(disc, "_data_term", fake)
        assert disc.discrepancy_alpha(None, np.eye(4), target=target).factors is None  # not asked for
        calls.clear()
        choice = disc.discrepancy_alpha(None, np.eye(4), target=target, keep_factors=True)
        below = values <= target
        # The factors at the chosen alpha come with it when it was the last alpha evaluated.
        assert (choice.factors is not None) == (choice.alpha == calls[-1])
        if choice.factors is not None:
            assert choice.factors == [("factor at", choice.alpha)] * 3
        if below[-1]:
            assert choice.alpha == pytest.approx(DEFAULT_ALPHA) and choice.bounded == "high" and len(calls) == 1
            assert choice.factors is not None
        elif not below[0]:
            assert choice.alpha == pytest.approx(1e-4) and choice.bounded == "low" and len(calls) == 2
            assert choice.factors is not None
        else:
            j = int(np.nonzero(~below)[0][0])
            assert DISCREPANCY_ALPHAS[j - 1] * (1 - 1e-12) <= choice.alpha <= DISCREPANCY_ALPHAS[j] * (1 + 1e-12)
            assert len(calls) <= 2 + int(np.ceil(np.log2(len(logs)))) + 1


def test_nnls_one_factor_route_hands_over_to_direct_solves(monkeypatch):
    """If the active-set system of the one-factor route is not numerically SPD mid-way, the
    pivoting continues with direct passive-set factorisations and still reaches the optimum."""
    import mi_bivariate.solve.nnls as nnls_mod

    a_mat, rhs = _problem("active", 1)
    g, b = a_mat.T @ a_mat, a_mat.T @ rhs
    expected, _ = sopt.nnls(a_mat, rhs, maxiter=100 * a_mat.shape[1])
    calls = []
    original = nnls_mod._SchurSolver.__call__

    def failing(self, passive):
        calls.append(int(np.sum(~passive)))
        if len(calls) > 1:
            raise np.linalg.LinAlgError("forced")
        return original(self, passive)

    monkeypatch.setattr(nnls_mod._SchurSolver, "__call__", failing)
    res = nnls_gram(g, b, passive=np.ones(b.size, bool))
    assert len(calls) == 2 and res.method == "bpp" and res.kkt_violation < 1e-12
    np.testing.assert_allclose(res.x, expected, rtol=0, atol=1e-9 * np.abs(expected).max())
    c, lower = res.factor  # still the whole G's factor, not the last passive set's
    u = np.tril(c).T if lower else np.triu(c)
    np.testing.assert_allclose(u.T @ u, g, rtol=0, atol=1e-12 * np.abs(g).max())


def test_nnls_one_factor_route_polishes_round_off_with_one_direct_solve(monkeypatch):
    """Nearly collinear columns (cond ~1e12): the one-factor route's answer misses the KKT
    tolerance by round-off (cond(G), not cond(G_FF)); one direct solve on the final passive set
    restores it, and the result says 'bpp', not the fallback."""
    import mi_bivariate.solve.nnls as nnls_mod

    rng = np.random.default_rng(0)
    a_mat = rng.standard_normal((120, 40))
    rhs = a_mat @ np.r_[3 * np.ones(5), -np.abs(rng.standard_normal(35))] + 0.1 * rng.standard_normal(120)
    a_mat = a_mat[:, :1] + 1e-6 * a_mat
    expected, _ = sopt.nnls(a_mat, rhs, maxiter=100 * a_mat.shape[1])
    direct = []
    original = nnls_mod._passive_solve
    monkeypatch.setattr(nnls_mod, "_passive_solve", lambda *args: direct.append(1) or original(*args))
    res = nnls_gram(a_mat.T @ a_mat, a_mat.T @ rhs, passive=np.ones(40, bool))
    assert res.method == "bpp" and res.kkt_violation < 1e-12 and len(direct) == 1
    np.testing.assert_allclose(res.x, expected, rtol=0, atol=1e-9 * np.abs(expected).max())
    assert res.factor is not None  # the whole G's factor, for the confidence


@pytest.mark.parametrize("lower", [False, True])
def test_inverse_diagonals_from_the_priors_entries_match_dense(lower, monkeypatch):
    """diag(X^-1) and diag(X^-1 gram) by 1 - diag(X^-1 Q) (Q = X - gram given by its entries,
    repeated diagonal entries included) equal the dense computation, for both triangles of the
    factor."""
    import scipy.linalg as sla

    from mi_bivariate.solve.common import gil_free, inverse_diagonals, sparse_entries

    rng = np.random.default_rng(3)
    n = 50
    b_mat = rng.standard_normal((200, n))
    gram = b_mat.T @ b_mat
    r_mat = np.diff(np.eye(n), 2, axis=0)
    penalty = 0.3 * r_mat.T @ r_mat
    precision = rng.uniform(0.1, 1.0, n)
    x = gram + penalty + np.diag(precision)
    rows, cols, values = sparse_entries(penalty)
    diag = np.arange(n)
    prior = (np.r_[rows, diag], np.r_[cols, diag], np.r_[values, precision])  # the diagonal twice
    with monkeypatch.context() as patch:  # a few diagonals: from the inverse factor, never a whole inverse
        patch.setattr(gil_free, "potri", _refuse)
        var, resolution = inverse_diagonals(x, gram, sla.cho_factor(x, lower=lower), prior=prior)
    inv = np.linalg.inv(x)
    np.testing.assert_allclose(var, np.diag(inv), rtol=1e-10)
    np.testing.assert_allclose(resolution, np.diag(inv @ gram), rtol=0, atol=1e-10)
    # The factor's memory given away, and no factor given: the same.
    for factor, overwrite in ((sla.cho_factor(x, lower=lower), True), (None, False)):
        again = inverse_diagonals(x, gram, factor, prior=prior, overwrite_factor=overwrite)
        np.testing.assert_allclose(again[0], var, rtol=1e-12)
        np.testing.assert_allclose(again[1], resolution, rtol=0, atol=1e-12)
    # A prior spread over every diagonal: read from potri's whole inverse, not from the inverse factor.
    c = rng.standard_normal((n, n))
    dense_prior = 0.01 * c @ c.T
    x = gram + dense_prior
    with monkeypatch.context() as patch:
        patch.setattr(gil_free, "trtri", _refuse)
        var, resolution = inverse_diagonals(x, gram, sla.cho_factor(x, lower=lower), prior=sparse_entries(dense_prior))
    inv = np.linalg.inv(x)
    np.testing.assert_allclose(var, np.diag(inv), rtol=1e-9)
    np.testing.assert_allclose(resolution, np.diag(inv @ gram), rtol=0, atol=1e-9)


def _refuse(*args, **kwargs):
    raise AssertionError("this route must not run here")


@pytest.mark.parametrize("alpha, pair_rule", [(None, "evidence"), ("gcv", "evidence"), (None, "residual")])
def test_solve_is_the_same_on_any_number_of_worker_threads(monkeypatch, alpha, pair_rule):
    """The channels run on worker threads (mi_bivariate.threads): every result is bit-identical to
    the one-after-another solve, for each alpha and pair rule, the two stages and the confidence."""
    L = _lighting(200, 31)
    I = np.einsum("mnk,nk->mk", L.astype(np.float64), _truth(32).reshape(N, 3))
    I *= 1 + 0.02 * np.random.default_rng(33).standard_normal(I.shape)
    mean = np.full((N_T, N_S, 3), float(np.mean(_truth(32))))
    results = {}
    for threads in ("1", "2", "3"):
        monkeypatch.setenv("MI_BIVARIATE_SOLVE_THREADS", threads)
        first = solve(L, I, _prior(), alpha, n_t=N_T, n_s=N_S, pair_rule=pair_rule)
        second = solve(L, I, _prior(), first.alphas, n_t=N_T, n_s=N_S, mean=mean, mean_std=0.5 * mean,
                       pairs=tuple(sorted(set(first.winner))), winner=first.winner)
        results[threads] = (first, second)
        # The discrepancy principle's factors were handed to the solve, not kept with the result, and
        # the solve from them is the solve at that alpha given.
        assert first.alpha_choice is None or first.alpha_choice.factors is None
        if alpha is None:
            given = solve(L, I, _prior(), first.alphas, n_t=N_T, n_s=N_S, pair_rule=pair_rule)
            np.testing.assert_array_equal(given.table, first.table)
            np.testing.assert_array_equal(given.resolution, first.resolution)
            for pair in first.pairs:  # the float32 table alone would not see a fallback's answer
                assert given.pairs[pair].method == first.pairs[pair].method
                np.testing.assert_array_equal(given.pairs[pair].iterations, first.pairs[pair].iterations)
                np.testing.assert_array_equal(given.pairs[pair].log_evidence, first.pairs[pair].log_evidence)
    for threads in ("2", "3"):
        for one, many in zip(results["1"], results[threads]):
            assert one.winner == many.winner
            np.testing.assert_array_equal(one.alphas, many.alphas)
            np.testing.assert_array_equal(one.table, many.table)
            for name in ("resolution", "posterior_std", "measured"):
                np.testing.assert_array_equal(getattr(one, name), getattr(many, name))
            for pair in one.pairs:
                for name in ("log_evidence", "gcv", "relative_residual", "data_term"):
                    np.testing.assert_array_equal(getattr(one.pairs[pair], name), getattr(many.pairs[pair], name))


def test_stage_one_starts_from_the_discrepancy_factors_of_its_own_systems(monkeypatch):
    """With a table prior (its diagonal in every system) and alpha at the bottom of its range, the
    discrepancy principle's factors are taken by the first variant's solves (three factorisations
    fewer) and give what the solve at that alpha given gives: tables, NNLS method and iterations,
    and the evidence (whose log det comes from the factor)."""
    from functools import partial

    import mi_bivariate.solve.nnls as nnls_mod
    import mi_bivariate.solve.regularised as reg

    monkeypatch.setenv("MI_BIVARIATE_SOLVE_THREADS", "3")
    monkeypatch.setattr(reg, "discrepancy_alpha", partial(reg.discrepancy_alpha, target=1e-12))  # "low"
    L = _lighting(200, 41)
    truth = _truth(42)
    I = np.einsum("mnk,nk->mk", L.astype(np.float64), truth.reshape(N, 3))
    I *= 1 + 0.02 * np.random.default_rng(43).standard_normal(I.shape)
    mean = np.clip(truth, 0.05, None) * np.array([0.8, 1.0, 1.3])  # differs per channel
    calls = []
    real = nnls_mod.cholesky
    monkeypatch.setattr(nnls_mod, "cholesky", lambda x: calls.append(1) or real(x))
    first = solve(L, I, _prior(), n_t=N_T, n_s=N_S, mean=mean, mean_std=0.5 * mean)
    from_discrepancy = len(calls)
    calls.clear()
    given = solve(L, I, _prior(), first.alphas, n_t=N_T, n_s=N_S, mean=mean, mean_std=0.5 * mean)
    assert first.alpha_choice.bounded == "low" and first.alpha_choice.factors is None
    assert from_discrepancy == len(calls) - 3
    np.testing.assert_array_equal(given.table, first.table)
    for pair in first.pairs:
        assert given.pairs[pair].method == first.pairs[pair].method
        np.testing.assert_array_equal(given.pairs[pair].iterations, first.pairs[pair].iterations)
        np.testing.assert_array_equal(given.pairs[pair].log_evidence, first.pairs[pair].log_evidence)


def test_nnls_ignores_a_factor_of_another_system():
    a_mat, rhs = _problem("well", 5)
    g, b = a_mat.T @ a_mat, a_mat.T @ rhs
    other = g + np.diag(np.full(g.shape[0], 1e-3 * np.mean(np.diag(g))))
    from mi_bivariate.solve.lapack import cho_factor

    plain = nnls_gram(g, b, np.ones(b.size, bool))
    right = nnls_gram(g, b, np.ones(b.size, bool), factor=cho_factor(g))
    wrong = nnls_gram(g, b, np.ones(b.size, bool), factor=cho_factor(other))
    for result in (right, wrong):
        np.testing.assert_array_equal(result.x, plain.x)
        assert result.log_det == plain.log_det and result.iterations == plain.iterations


def test_gcv_minimum_of_an_exact_fit_takes_no_log_of_zero():
    """An exact fit scores 0 beside a positive score (``recover --normals 1 --alpha gcv``): the parabola
    through log GCV is skipped, not fed log(0) (numpy's divide-by-zero warning reached the user)."""
    from mi_bivariate.solve.gcv import _minimum

    alphas = np.array([1e-3, 1e-2, 1e-1, 1.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        assert _minimum(alphas, np.array([1e-14, 0.0, 1e-14, 1.0])) == (1e-2, 0.0)
        assert _minimum(alphas, np.array([np.inf, 2.0, 1.0, 2.0])) == pytest.approx((0.1, 1.0), rel=1e-12)


def test_gcv_skips_alphas_an_ill_conditioned_prior_cannot_factorise():
    """A prior whose sigmas span 10 decades left G + lambda P numerically indefinite at some alphas: GCV
    raised LinAlgError (a traceback from ``recover --alpha gcv``); those alphas are now no candidates."""
    rng = np.random.default_rng(0)
    L = rng.random((200, N, 3)).astype(np.float32)
    clean = np.einsum("mnk,nk->mk", L.astype(np.float64), rng.random((N, 3)))
    I = (clean * (1 + 0.05 * rng.standard_normal(clean.shape))).astype(np.float32)
    data = prepare_data_term(L, I, 0.05 * np.abs(I) + 1e-6)
    sigma = np.ones((N_T, N_S))
    sigma[:, :2] = 1e-10
    penalty = Prior({"diffuse": (sigma, np.ones((N_T, N_S))), "gloss": (sigma, np.ones((N_T, N_S)))}
                    ).penalty_matrix("gloss")
    curve = gcv_curve(data, penalty, 1)
    assert np.isinf(curve.scores).any() and np.isfinite(curve.alpha) and np.isfinite(curve.score)


def test_row_sigma_by_hand():
    """``sigma^2 = model(I) + a I + b`` per image, with ``model`` each form of the model error at
    ``level = max(I, d Ibar)`` (``Ibar``: the image's channel mean of ``max(I, 0)``), written out for
    two images of three rows."""
    from mi_bivariate.solve import row_sigma
    from mi_bivariate.solve.data_term import DARK_FRACTION

    I = np.array([[1.0, 0.0, 2.0], [3.0, 0.5, -1.0], [0.001, 1.5, 4.0],
                  [10.0, 20.0, 0.0], [30.0, 0.1, 0.0], [50.0, 60.0, 0.0]])
    index = np.array([0, 0, 0, 1, 1, 1])
    noise = [(0.02, 1e-4), ((0.1, 0.2, 0.3), 0.5)]
    c = 0.03
    for form in ("sqrt", "relative", "constant"):
        want = np.empty_like(I)
        for m in range(6):
            k = index[m]
            rows = I[index == k]
            for ch in range(3):
                mean = np.maximum(rows[:, ch], 0.0).mean() or 1.0
                level = max(I[m, ch], DARK_FRACTION * mean)
                model = {"sqrt": c * c * mean * level, "relative": (c * level) ** 2, "constant": (c * mean) ** 2}[form]
                a, b = noise[k]
                a = a[ch] if isinstance(a, tuple) else a
                want[m, ch] = math.sqrt(model + a * max(I[m, ch], 0.0) + b)
        got = row_sigma(I, index, noise, model_error=c, form=form)
        np.testing.assert_allclose(got, want, rtol=1e-12, err_msg=form)


def test_kkt_violation_sees_an_infeasible_point_with_a_zero_gradient():
    """``x = (-1, 1)`` for ``G = I, b = (-1, 1)``: the gradient is 0 but ``x_0 < 0`` breaks ``x >= 0``."""
    from mi_bivariate.solve.nnls import kkt_violation

    G, b = np.eye(2), np.array([-1.0, 1.0])
    assert kkt_violation(G, b, np.array([-1.0, 1.0])) >= 1.0
    assert kkt_violation(G, b, np.array([0.0, 1.0])) == 0.0


@pytest.mark.parametrize("lower", [False, True])
def test_inverse_diagonals_without_the_priors_entries_match_dense(lower):
    """Without the prior's entries, diag(X^-1 gram) is read from one triangle T of potri's inverse as
    ``sum_j P_ij + sum_j P_ji - P_ii`` (``P = T * gram``): against the dense inverse."""
    import scipy.linalg as sla

    from mi_bivariate.solve.common import inverse_diagonals

    rng = np.random.default_rng(8)
    n = 30
    b_mat = rng.standard_normal((80, n))
    gram = b_mat.T @ b_mat
    x = gram + np.diag(rng.uniform(0.5, 2.0, n))
    var, resolution = inverse_diagonals(x, gram, sla.cho_factor(x, lower=lower))
    inv = np.linalg.inv(x)
    np.testing.assert_allclose(var, np.diag(inv), rtol=1e-10)
    np.testing.assert_allclose(resolution, np.diag(inv @ gram), rtol=0, atol=1e-10)


def test_check_alpha_accepts_exactly_zero_and_its_documented_range():
    """Given alphas: 0, or between 1e-12 and 1e6 (beyond, the normal equations lose the data term or
    the prior in float64), one or three of them."""
    from mi_bivariate.solve.common import ALPHA_RANGE

    assert ALPHA_RANGE == (1e-12, 1e6)
    np.testing.assert_array_equal(check_alpha(0.0), np.zeros(3))
    np.testing.assert_array_equal(check_alpha([1e-12, 1e6, 0.0]), [1e-12, 1e6, 0.0])
    assert check_alpha("0.5")[0] == 0.5
    for bad in (1e-13, 2e6, [1e-2, 1e-2, 1e7], [1e-2, 5e-13, 1e-2], -1e-3, np.inf, "one", [1.0, 2.0]):
        with pytest.raises(InputError, match="alpha"):
            check_alpha(bad)


def test_discrepancy_alpha_with_a_table_prior_against_direct_solves():
    """With the basis prior's fixed diagonal Gaussian (``extra = (precision, precision * mean)``) in
    the system and the right-hand side, the chosen alpha is where the data term of the direct solve
    ``(gram + lambda P + diag(precision)) f = rhs + precision * mean`` meets the target."""
    L, I, sigma = _noisy_problem(0.05)
    data = prepare_data_term(L, I, sigma)
    penalty = _prior().penalty_matrix("diffuse")
    rng = np.random.default_rng(12)
    mean = rng.uniform(0.0, 2.0, (N, 3)) * data.level
    precision = 0.2 * np.mean(np.diagonal(data.gram, axis1=1, axis2=2), axis=1) * rng.uniform(0.5, 1.5, (N, 3))

    def rho(alpha):
        out = []
        for k in range(3):
            lam = alpha / (N * data.level[k] ** 2)
            f = np.linalg.solve(data.gram[k] + lam * penalty + np.diag(precision[:, k]),
                                data.rhs[k] + precision[:, k] * mean[:, k])
            out.append(data.yy[k] - 2 * f @ data.rhs[k] + f @ data.gram[k] @ f)
        return float(np.mean(out))

    grid = 10.0 ** np.arange(-2.0, 3.01, 0.5)
    for alpha in (0.1, 3.0, 100.0):
        target = rho(alpha)
        choice = discrepancy_alpha(data, penalty, target=target, alphas=grid, extra=(precision, precision * mean))
        assert choice.bounded == ""
        assert rho(choice.alpha) == pytest.approx(target, rel=0.02)


def test_every_input_check_of_the_solve_names_its_problem():
    """Each check of ``validate_problem`` and ``grid_shape`` on its own: more observations than lighting rows
    (the check compared the counts one way only), no columns, a dtype that is not a number (complex, text),
    and a column count that is no square grid without ``n_t, n_s``: an InputError, never a traceback."""
    L = _lighting(20, 0)
    I = np.ones((20, 3))
    prior = Prior.uniform(N_T, N_S)
    with pytest.raises(InputError, match="10 rows but there are 20 observations"):
        solve(L[:10], I, prior, 0.1)
    with pytest.raises(InputError, match="no columns"):
        solve(L[:, :0], I, prior, 0.1)
    with pytest.raises(InputError, match="non-numeric dtype complex"):
        solve(L.astype(np.complex128), I, prior, 0.1)
    with pytest.raises(InputError, match="observations I: has non-numeric dtype"):
        solve(L, I.astype(str), prior, 0.1)
    for n in (24, 15):  # 24 = 5 x 5 - 1, 15 = 4 x 4 - 1: no square
        with pytest.raises(InputError, match=f"{n} columns is not a square grid"):
            solve(L[:, :n], I, prior, 0.1)


def test_grid_is_the_priors_own_when_it_is_not_square():
    """Without ``n_t, n_s`` a prior of ``N`` nodes gives its own grid, rows ``n_t`` and columns ``n_s``
    (column ``it * n_s + is``): a 6 x 5 prior and a 5 x 6 one read the same columns as different tables."""
    L = _lighting(150, 14)
    truth = _truth(15)
    I = np.einsum("mnk,nk->mk", L.astype(np.float64), truth.reshape(N, 3))
    tall = solve(L, I, Prior.uniform(N_T, N_S), 0.0)
    wide = solve(L, I, Prior.uniform(N_S, N_T), 0.0)
    assert tall.table.shape == (N_T, N_S, 3) and wide.table.shape == (N_S, N_T, 3)
    np.testing.assert_allclose(tall.table, truth, atol=1e-6)  # column it * n_s + is is node (it, is)
    np.testing.assert_array_equal(wide.table.reshape(N, 3), tall.table.reshape(N, 3))


def test_a_black_channel_gives_a_zero_table_and_no_nan():
    """An image with nothing in one channel (a pure-colour material): that channel's best constant level is
    0, its table is 0 and explains the image exactly (relative residual 0, not NaN or infinity), and the
    other channels are solved as without it, every number finite."""
    L = _lighting(150, 16)
    truth = _truth(17)
    I = np.einsum("mnk,nk->mk", L.astype(np.float64), truth.reshape(N, 3))
    I *= 1 + 0.03 * np.random.default_rng(18).standard_normal(I.shape)
    I[:, 2] = 0.0
    sigma = 0.03 * np.abs(I) + 1e-3 * np.abs(I).mean(axis=0).max()
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        result = solve(L, I, _prior(), 0.3, n_t=N_T, n_s=N_S, sigma=sigma)
        colour = solve(L[:, :, :2].repeat([1, 2], axis=2), I[:, [0, 1, 1]], _prior(), 0.3, n_t=N_T, n_s=N_S,
                       sigma=sigma[:, [0, 1, 1]])
    assert result.lambertian[2] == 0.0
    np.testing.assert_array_equal(result.table[:, :, 2], 0.0)
    for sol in result.pairs.values():
        assert sol.relative_residual[2] == 0.0 and sol.data_term[2] == 0.0
        for name in ("data_term", "prior_term", "relative_residual", "log_evidence", "kkt_violation"):
            assert np.all(np.isfinite(getattr(sol, name))), name
    np.testing.assert_array_equal(result.table[:, :, :2], colour.table[:, :, :2])


def test_kkt_violation_is_relative_to_the_scales_of_x_and_the_gradient():
    """The documented natural residual by hand: ``x = 0`` where ``b`` asks for a positive value violates by
    exactly 1 whatever ``b``'s size (``g / g_scale = -b / max|b|``), and scaling ``b`` and ``x`` together
    changes nothing (``x / max|x|``)."""
    G = np.eye(2)
    for c in (1e-3, 1.0, 4.0, 1e6):
        assert kkt_violation(G, c * np.array([1.0, -1.0]), np.zeros(2)) == pytest.approx(1.0, rel=1e-15)
        # x = c (-0.5, 1), b = c (1, 1): g = c (-1.5, 0), x_scale = c, g_scale = 2 c: |min(-0.5, -0.75)| = 0.75
        assert kkt_violation(G, c * np.array([1.0, 1.0]), c * np.array([-0.5, 1.0])) == pytest.approx(0.75, rel=1e-15)


def test_nnls_fixes_the_nodes_no_pixel_sees_at_zero():
    """Columns of ``A`` that are zero (an st node no pixel sees, no prior): ``G``'s row and column and ``b``'s
    entry vanish there; the solve sets them to 0 and the rest is ``scipy.optimize.nnls`` on the seen columns,
    from either start."""
    a_mat, rhs = _problem("active", 3)
    unseen = [0, 7, 8, 39]
    a_mat[:, unseen] = 0.0
    seen = np.setdiff1d(np.arange(a_mat.shape[1]), unseen)
    expected = np.zeros(a_mat.shape[1])
    expected[seen] = sopt.nnls(a_mat[:, seen], rhs, maxiter=100 * a_mat.shape[1])[0]
    g, b = a_mat.T @ a_mat, a_mat.T @ rhs
    for start in (False, True):
        res = nnls_gram(g, b, passive=np.full(b.size, start))
        assert res.method == "bpp" and res.kkt_violation < 1e-12
        np.testing.assert_array_equal(res.x[unseen], 0.0)
        np.testing.assert_allclose(res.x, expected, rtol=0, atol=1e-9 * np.abs(expected).max())
    # The seen columns' pivoting stopped after one solve: their fallback's answer, and the result says so.
    res = nnls_gram(g, b, passive=np.ones(b.size, bool), max_iter=1)
    assert res.method == "bpp+nnls-fallback" and res.kkt_violation < KKT_TOLERANCE
    np.testing.assert_allclose(res.x, expected, rtol=0, atol=1e-9 * np.abs(expected).max())


def test_solve_with_a_node_no_pixel_sees():
    """A lighting matrix whose column is zero in every channel (a node the image does not reach) is no
    error: the smoothness prior fills that node in from its neighbours, as the stacked NNLS does."""
    L = _lighting(150, 19)
    L[:, 12] = 0.0
    I = np.einsum("mnk,nk->mk", L.astype(np.float64), _truth(20).reshape(N, 3))
    prior, alpha = _prior(), 0.3
    result = solve(L, I, prior, alpha, n_t=N_T, n_s=N_S, pairs=("gloss",))
    sigma = row_sigma(I)
    w = 1.0 / (sigma * np.sqrt(len(I)))
    for k in range(3):
        a_k = L[:, :, k].astype(np.float64) * w[:, k, None]
        y_k = I[:, k] * w[:, k]
        ones = np.ones(N)
        level = (ones @ a_k.T @ y_k) / (ones @ a_k.T @ a_k @ ones)
        reg = np.sqrt(alpha / (N * level**2)) * prior.regulariser("gloss").toarray()
        expected = sopt.nnls(np.vstack([a_k, reg]), np.r_[y_k, np.zeros(reg.shape[0])], maxiter=100 * N)[0]
        np.testing.assert_allclose(result.table[:, :, k].ravel(), expected, rtol=1e-5, atol=1e-6 * expected.max())
    assert np.all(result.table.reshape(N, 3)[12] > 0)


@pytest.mark.parametrize("table_prior", [False, True])
def test_gcv_curve_of_a_diagonal_problem_in_closed_form(table_prior):
    """Each pixel lit by one node and a diagonal penalty: every matrix is diagonal, so the solution, the
    data term and ``tr(H) = sum_i g_i / (g_i + lambda p_i + d_i)`` have closed forms (Hutchinson's estimate
    with +-1 probes is exact on a diagonal), and so does ``GCV = rho / (1 - tr(H) / M)^2`` at every alpha,
    with the basis prior's fixed diagonal ``d`` and shift ``s`` in the system and the right-hand side."""
    rng = np.random.default_rng(5)
    n, per = 6, 3
    m = n * per
    node = np.repeat(np.arange(n), per)
    L = np.zeros((m, n, 3), np.float32)
    L[np.arange(m), node] = rng.uniform(0.5, 2.0, (m, 3))
    I = np.einsum("mnk,nk->mk", L.astype(np.float64), rng.uniform(0.2, 1.0, (n, 3))) * rng.uniform(0.8, 1.2, (m, 3))
    sigma = rng.uniform(0.05, 0.2, (m, 3))
    data = prepare_data_term(L, I, sigma)
    p = rng.uniform(0.5, 2.0, n)
    alphas = 10.0 ** np.arange(-3.0, 2.01, 1.0)
    for k in range(3):
        a = L[np.arange(m), node, k].astype(np.float64) / (sigma[:, k] * np.sqrt(m))
        y = I[:, k] / (sigma[:, k] * np.sqrt(m))
        g = np.bincount(node, a * a, n)
        b = np.bincount(node, a * y, n)
        level = b.sum() / g.sum()
        d, s = (rng.uniform(0.5, 2.0, n) * g.mean(), rng.uniform(0.0, 1.0, n) * b.mean()) if table_prior else \
            (np.zeros(n), np.zeros(n))
        for probes in (1, 16):
            curve = gcv_curve(data, np.diag(p), k, alphas=alphas, probes=probes,
                              extra=(d, s) if table_prior else None)
            for alpha, score, dof in zip(curve.alphas, curve.scores, curve.dof):
                x = g + alpha / (n * level**2) * p + d
                f = (b + s) / x
                rho = y @ y - 2 * f @ b + g @ f**2
                trace = np.sum(g / x)
                assert dof == pytest.approx(trace, rel=1e-12)
                assert score == pytest.approx(rho / (1 - trace / m) ** 2, rel=1e-10)


def test_gcv_refuses_a_prior_it_cannot_factorise_at_any_alpha():
    """Where ``gram + lambda P`` fails to factorise at every scanned alpha (here an indefinite ``P``), GCV has
    no candidate: an InputError that says so, not the first alpha of the scan with an infinite score."""
    from mi_bivariate.errors import InputError

    L, I, sigma = _noisy_problem(0.05)
    data = prepare_data_term(L, I, sigma)
    scale = float(np.mean(np.diag(data.gram[0]))) * N * data.level[0] ** 2
    with pytest.raises(InputError, match="cannot be factorised at any alpha"):
        gcv_curve(data, -1e6 * scale * np.eye(N), 0, alphas=(1e-2, 1.0))


def test_gcv_minimum_is_the_vertex_of_the_parabola_in_log10_alpha():
    """Scores that are exactly ``exp(c (log10 alpha - v)^2 + e)`` about their smallest grid point: the
    refined minimum is the vertex ``10^v`` with score ``exp(e)``; a minimum at either end of the grid is
    that grid point, unrefined."""
    from mi_bivariate.solve.gcv import _minimum

    alphas = 10.0 ** np.arange(-4.0, 1.01, 1.0)
    x = np.log10(alphas)
    for vertex, c in ((-1.3, 0.7), (-2.8, 2.0), (-2.0, 0.1)):
        alpha, score = _minimum(alphas, np.exp(c * (x - vertex) ** 2 + 0.4))
        assert alpha == pytest.approx(10.0**vertex, rel=1e-9) and score == pytest.approx(np.exp(0.4), rel=1e-9)
    rising = np.exp(np.arange(6.0))
    assert _minimum(alphas, rising) == (1e-4, 1.0)
    assert _minimum(alphas, rising[::-1]) == pytest.approx((10.0, 1.0), rel=1e-12)


def test_entry_helpers_add_repeated_entries_and_leave_a_given_factor_alone():
    """``add_entries`` and ``quadratic_form`` against the dense matrix their entries stand for, repeated
    entries adding up as documented; ``inverse_diagonals`` given a factor without ``overwrite_factor`` leaves
    it as it was (the caller may still need it), by either route."""
    import scipy.linalg as sla

    from mi_bivariate.solve.common import add_entries, inverse_diagonals, quadratic_form, sparse_entries

    rng = np.random.default_rng(6)
    n = 12
    rows, cols = np.r_[0, 3, 3, 5, 0, 11], np.r_[0, 4, 4, 5, 0, 2]
    values = rng.uniform(0.5, 2.0, rows.size)
    dense = np.zeros((n, n))
    for r, c, v in zip(rows, cols, values):
        dense[r, c] += v
    base = rng.standard_normal((n, n))
    np.testing.assert_allclose(add_entries(base.copy(), (rows, cols, values), 0.3), base + 0.3 * dense, rtol=1e-15)
    f = rng.standard_normal(n)
    assert quadratic_form((rows, cols, values), f) == pytest.approx(f @ dense @ f, rel=1e-14)
    b_mat = rng.standard_normal((40, n))
    gram = b_mat.T @ b_mat
    prior = 0.5 * np.diag(np.r_[2.0, np.ones(n - 1)]) + 0.1 * (np.eye(n, k=1) + np.eye(n, k=-1))
    x = gram + prior
    for entries in (sparse_entries(prior), None):
        factor = sla.cho_factor(x, lower=True)
        kept = factor[0].copy()
        inverse_diagonals(x, gram, factor, prior=entries)
        np.testing.assert_array_equal(factor[0], kept)


def test_nnls_hands_back_only_a_factor_of_the_whole_system():
    """From an empty start the passive-set solves factorise ``G_FF`` only: where constraints end active, the
    result carries no factor (the confidence would read ``G_FF``'s as ``G``'s) and factorises ``G`` itself."""
    for kind, seed in (("active", 2), ("well", 3)):
        a_mat, rhs = _problem(kind, seed)
        res = nnls_gram(a_mat.T @ a_mat, a_mat.T @ rhs)
        assert np.any(res.x == 0) and res.factor is None


def test_nnls_answer_is_non_negative_where_an_exact_fit_touches_zero():
    """Noiseless data ``a = A x*`` with ``x*`` zero on 4 of 10 coordinates (full column rank ``A``): the unique
    solution is ``x*`` itself, and there the gradient is 0 too, so the passive-set solve lands on the zeros
    with round-off of either sign (~-1e-16, below the exchange threshold). The answer must still be ``>= 0``
    (the result's contract): without the final clip, most of these seeds returned -1e-16."""
    for seed in range(10):
        rng = np.random.default_rng(seed)
        a_mat = rng.standard_normal((30, 10))
        truth = rng.random(10)
        truth[:4] = 0.0
        g, b = a_mat.T @ a_mat, a_mat.T @ (a_mat @ truth)
        for start in (False, True):
            res = nnls_gram(g, b, passive=np.full(10, start))
            assert res.method == "bpp" and res.kkt_violation < 1e-12
            assert np.all(res.x >= 0.0), (seed, start, res.x.min())
            np.testing.assert_allclose(res.x, truth, rtol=0, atol=1e-12)


def test_nnls_falls_back_exactly_when_the_violation_exceeds_the_given_tolerance():
    """Closed form: ``G = [[1, -1/2], [-1/2, 1]]``, ``b = G (1, -c)``. The one passive-set solve from the full
    start (``max_iter=1``) is ``(1, -c)``, clipped to ``(1, 0)``: gradient ``(-c/2, c)``, ``x_scale = 1``,
    ``g_scale = max|b| + max(|G| x) = 2 + c/2``, violation ``v = (c/2) / (2 + c/2)``. The solution is
    ``(1 + c/2, 0)`` (``x_1`` active, ``g_1 = 3c/4 > 0``). ``tol`` is the accepted violation: any ``tol`` below
    ``v`` (even ``v / 2``) sends the solve to the fallback and its exact answer, any above keeps the clipped one."""
    c = 2e-8
    G = np.array([[1.0, -0.5], [-0.5, 1.0]])
    b = G @ np.array([1.0, -c])
    v = (c / 2) / (2 + c / 2)
    kept = nnls_gram(G, b, passive=np.ones(2, bool), max_iter=1, tol=2 * v)
    assert kept.method == "bpp"
    np.testing.assert_allclose(kept.x, [1.0, 0.0], rtol=1e-14, atol=0)
    assert kept.kkt_violation == pytest.approx(v, rel=1e-6)  # g's round-off (~1e-16) over c
    for tol in (v / 2, v / 1.5, KKT_TOLERANCE):
        assert v > tol
        res = nnls_gram(G, b, passive=np.ones(2, bool), max_iter=1, tol=tol)
        assert res.method == "bpp+nnls-fallback" and res.kkt_violation < 1e-15, tol
        np.testing.assert_allclose(res.x, [1.0 + c / 2, 0.0], rtol=1e-15, atol=0)


def test_nnls_fallback_of_a_rank_deficient_system_is_scipys_answer():
    """``A`` of rank 5 with 10 columns: the minimisers form a set, and ``G``'s 5 null eigenvalues are round-off
    (~1e-16 of the largest, either sign). The fallback drops them, so its system has ``A``'s row space exactly and
    ``scipy.optimize.nnls`` on it takes the steps it takes on ``A`` itself: the same answer. Keeping the
    round-off eigenvalues that happen to be positive (``d = v^T b / sqrt(w)`` of round-off over round-off) moved
    the answer along ``A``'s null space by up to its own size on 2 of these 6 seeds."""
    for seed in range(6):
        rng = np.random.default_rng(seed)
        a_mat = rng.standard_normal((30, 5)) @ rng.standard_normal((5, 10))
        rhs = a_mat @ rng.standard_normal(10) + 0.1 * rng.standard_normal(30)
        expected, _ = sopt.nnls(a_mat, rhs, maxiter=1000)
        res = nnls_gram(a_mat.T @ a_mat, a_mat.T @ rhs, passive=np.ones(10, bool), max_iter=1)
        assert res.method == "bpp+nnls-fallback" and res.kkt_violation < KKT_TOLERANCE
        np.testing.assert_allclose(res.x, expected, rtol=0, atol=1e-10 * np.abs(expected).max(), err_msg=str(seed))


def test_prepare_data_term_refuses_bad_row_sigmas():
    """Given row sigmas must be finite, > 0 and shaped like I: a zero (an infinite weight), a NaN and a
    (M, 1) column each give an InputError."""
    from mi_bivariate.errors import InputError

    L = _lighting(20, 0)
    I = np.ones((20, 3))
    for sigma in (np.where(np.arange(60).reshape(20, 3) == 7, 0.0, 0.1), np.where(np.arange(60).reshape(20, 3) == 7,
                                                                                   np.nan, 0.1), np.full((20, 1), 0.1)):
        with pytest.raises(InputError, match="row sigmas"):
            prepare_data_term(L, I, sigma)


@pytest.mark.parametrize("table_prior", [False, True])
def test_confidence_maps_are_the_dense_posterior(table_prior):
    """The three confidence maps of both pairs (the kept one and the other, computed on first access) against
    the Gaussian posterior written out densely: with ``G = A^T A`` (``A = L / (sigma sqrt(M))``), ``lambda =
    alpha / (N level^2)`` per channel and ``X = G + lambda R^T R [+ D]`` (``D = diag(1 / (M std^2))``, the table
    prior), ``resolution = diag(X^-1 G)``, ``posterior_std = sqrt(diag(X^-1) / M)`` and ``measured = 1 -
    diag(X^-1) / diag(X_prior^-1)``, ``X_prior = lambda R^T R + D`` (without a table prior ``+ 1e-6 mean(diag G)``
    stands in for ``D``); the alphas differ per channel. Node 12 no pixel sees: its resolution is 0, and every
    map stays in its documented range [0, 1] (round-off gave -2e-16 there)."""
    L = _lighting(150, 24)
    L[:, 12] = 0.0
    truth = _truth(25)
    I = np.einsum("mnk,nk->mk", L.astype(np.float64), truth.reshape(N, 3))
    I *= 1 + 0.03 * np.random.default_rng(26).standard_normal(I.shape)
    prior, alphas = _prior(), np.array([0.3, 0.02, 2.0])
    m = L.shape[0]
    kwargs = {}
    if table_prior:
        mean = np.clip(truth, 0.05, None) * np.array([0.9, 1.1, 1.0])
        kwargs = dict(mean=mean, mean_std=np.random.default_rng(27).uniform(0.2, 0.6, mean.shape) * mean)
    result = solve(L, I, prior, alphas, n_t=N_T, n_s=N_S, **kwargs)
    w = 1.0 / (row_sigma(I) * np.sqrt(m))
    ones = np.ones(N)
    for k in range(3):
        a_k = L[:, :, k].astype(np.float64) * w[:, k, None]
        g = a_k.T @ a_k
        level = (ones @ a_k.T @ (I[:, k] * w[:, k])) / (ones @ g @ ones)
        lam = alphas[k] / (N * level**2)
        d = 1.0 / (m * kwargs["mean_std"][:, :, k].ravel() ** 2) if table_prior else np.zeros(N)
        ridge = d if table_prior else np.full(N, 1e-6 * np.mean(np.diag(g)))
        for pair, sol in result.pairs.items():
            r = prior.regulariser(pair).toarray()
            inv = np.linalg.inv(g + lam * r.T @ r + np.diag(d))
            prior_var = np.diag(np.linalg.inv(lam * r.T @ r + np.diag(ridge)))
            np.testing.assert_allclose(sol.resolution[:, :, k].ravel(), np.clip(np.diag(inv @ g), 0, 1),
                                       rtol=0, atol=1e-9, err_msg=pair)
            np.testing.assert_allclose(sol.posterior_std[:, :, k].ravel(), np.sqrt(np.diag(inv) / m), rtol=1e-9,
                                       err_msg=pair)
            np.testing.assert_allclose(sol.measured[:, :, k].ravel(), np.clip(1 - np.diag(inv) / prior_var, 0, 1),
                                       rtol=0, atol=1e-8, err_msg=pair)  # measured: ~1e-16 apart
            for name in ("resolution", "measured"):
                values = getattr(sol, name)[:, :, k]
                assert np.all((values >= 0) & (values <= 1)), (pair, name)
    for name in ("resolution", "posterior_std", "measured"):  # the kept pair's, per channel
        np.testing.assert_array_equal(getattr(result, name), np.stack(
            [getattr(result.pairs[wn], name)[:, :, k] for k, wn in enumerate(result.winner)], axis=-1))


def test_discrepancy_alpha_when_the_floor_fits_the_image_exactly(monkeypatch):
    """A data term of exactly 0 at the bottom of the bracket (an exact fit: ``recover --normals 1``): the regula
    falsi in ``(log alpha, log rho)`` takes ``log max(rho, 1e-300)`` there, so the chosen alpha is finite and
    inside the bracketing half decade, with no ``log(0)`` warning (its secant would be NaN). The factors come
    back only for all three channels together."""
    logs = np.log10(DISCREPANCY_ALPHAS)
    values = np.array([0.0, 0.0, 0.0, 30.0, 60.0])  # rho = 0 up to 1e-3, 30 at 10^-2.5
    assert len(values) == len(logs)

    def fake(data, entries, channels, alpha, extra):
        return float(np.interp(np.log10(alpha), logs, values)), [("factor at", alpha)] * len(channels)

    monkeypatch.setattr(disc, "_data_term", fake)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        choice = disc.discrepancy_alpha(None, np.eye(4), target=20.0)
        one = disc.discrepancy_alpha(None, np.eye(4), channels=(1,), target=20.0, keep_factors=True)
    assert choice.bounded == "" and 10.0**-3 < choice.alpha <= 10.0**-2.5
    assert one.alpha == choice.alpha and one.factors is None
    high = [disc.discrepancy_alpha(None, np.eye(4), channels=c, target=100.0, keep_factors=True)
            for c in ((0, 1, 2), (1,))]  # the default: the last alpha evaluated
    assert high[0].bounded == "high" and high[0].factors == [("factor at", high[0].alpha)] * 3
    assert high[1].bounded == "high" and high[1].factors is None


def test_data_term_is_the_weighted_system_written_out():
    """``prepare_data_term`` against the dense float64 products of ``A = L / (sigma sqrt(M))`` and ``y = I /
    (sigma sqrt(M))``: ``gram = A^T A``, ``rhs = A^T y`` and ``yy = y^T y``, so that ``f^T gram f - 2 rhs^T f + yy``
    is ``||y - A f||^2`` for any ``f``; ``level`` is the best non-negative constant table (``scipy.optimize.nnls``
    on the one column ``A 1``), 0 for a channel whose image is noise about black, mostly below 0. An unknown
    model-error form is an InputError naming it."""
    L = _lighting(90, 27)
    rng = np.random.default_rng(28)
    I = np.einsum("mnk,nk->mk", L.astype(np.float64), _truth(29).reshape(N, 3))
    I *= 1 + 0.02 * rng.standard_normal(I.shape)
    I[:, 2] = 0.01 * rng.standard_normal(90) - 0.005
    sigma = rng.uniform(0.01, 0.1, I.shape)
    data = prepare_data_term(L, I, sigma)
    m = len(I)
    for k in range(3):
        a = L[:, :, k].astype(np.float64) / (sigma[:, k, None] * np.sqrt(m))
        y = I[:, k] / (sigma[:, k] * np.sqrt(m))
        np.testing.assert_allclose(data.gram[k], a.T @ a, rtol=1e-12, atol=1e-14 * np.abs(a.T @ a).max())
        np.testing.assert_allclose(data.rhs[k], a.T @ y, rtol=1e-12, atol=1e-14 * np.abs(a.T @ y).max())
        assert data.yy[k] == pytest.approx(y @ y, rel=1e-13)
        f = rng.uniform(0.0, 1.0, N)
        assert f @ data.gram[k] @ f - 2 * data.rhs[k] @ f + data.yy[k] == pytest.approx(np.sum((y - a @ f) ** 2),
                                                                                       rel=1e-10)
        level = sopt.nnls(a.sum(axis=1)[:, None], y)[0][0]
        assert data.level[k] == pytest.approx(level, rel=1e-12, abs=0.0)
    assert data.level[2] == 0.0
    with pytest.raises(InputError, match="model-error form 'cubic'"):
        row_sigma(I, form="cubic")


def test_one_pair_is_kept_as_given_and_a_non_finite_table_prior_is_refused():
    """With one weight pair there is nothing to choose: it is kept as given (``pair_rule`` "given") and no
    evidence is computed for it (NaN), whatever the rule asked for. A table-prior mean with a NaN or an
    infinity is an InputError naming the mean, like a std of 0."""
    L = _lighting(60, 30)
    I = np.einsum("mnk,nk->mk", L.astype(np.float64), _truth(31).reshape(N, 3))
    data = prepare_data_term(L, I)
    for rule in ("evidence", "residual"):
        result = solve_prepared(data, _prior(), 0.3, n_t=N_T, n_s=N_S, pairs=("gloss",), pair_rule=rule)
        assert result.winner == ("gloss",) * 3 and result.pair_rule == "given"
        assert np.all(np.isnan(result.pairs["gloss"].log_evidence))
    std = np.ones((N_T, N_S, 3))
    for bad in (np.nan, np.inf):
        mean = np.ones((N_T, N_S, 3))
        mean[2, 3, 1] = bad
        with pytest.raises(InputError, match="mean and std must be finite"):
            solve_prepared(data, _prior(), 0.3, n_t=N_T, n_s=N_S, mean=mean, mean_std=std)


def test_gcv_keeps_the_pair_with_the_lower_score_and_its_alpha():
    """With ``alpha="gcv"`` each pair chooses its own alpha per channel, and the kept pair is the one with the
    lower GCV score; the result's alphas and table are, per channel, the kept pair's (here the pairs differ
    in alpha by up to a decade, and the kept pair differs between channels)."""
    L = _lighting(150, 1)
    I = np.einsum("mnk,nk->mk", L.astype(np.float64), _truth(2).reshape(N, 3))
    I *= 1 + 0.05 * np.random.default_rng(3).standard_normal(I.shape)
    result = solve(L, I, _prior(), "gcv", n_t=N_T, n_s=N_S)
    assert result.alpha_rule == result.pair_rule == "gcv" and len(set(result.winner)) == 2
    for k, w in enumerate(result.winner):
        other = "gloss" if w == "diffuse" else "diffuse"
        assert result.pairs[w].gcv[k] < result.pairs[other].gcv[k]
        assert result.alphas[k] == result.pairs[w].alpha[k] != result.pairs[other].alpha[k]
        np.testing.assert_array_equal(result.table[:, :, k], result.pairs[w].table[:, :, k])


def test_spd_inverse_of_a_singular_matrix_is_the_pseudo_inverse():
    """``spd_inverse`` (the confidence's dense route to the prior-only variance) as documented: the inverse of
    an SPD matrix, and ``numpy.linalg.pinv`` of a singular PSD one (rank 2 of 4), whose Cholesky fails."""
    rng = np.random.default_rng(13)
    b_mat = rng.standard_normal((2, 4))
    singular = b_mat.T @ b_mat
    np.testing.assert_allclose(spd_inverse(singular), np.linalg.pinv(singular), rtol=0, atol=1e-12)
    spd = singular + np.eye(4)
    np.testing.assert_allclose(spd_inverse(spd), np.linalg.inv(spd), rtol=0, atol=1e-12)


def test_inverse_diagonals_of_a_singular_system_are_the_pseudo_inverses():
    """A system ``X = gram + Q`` singular along a node that neither the data nor the prior reaches: no
    Cholesky factor (and none of a matrix with a NaN: LAPACK would hand back a NaN factor), so
    ``inverse_diagonals`` reads ``diag(X^+)`` and ``diag(X^+ gram)`` from numpy's pseudo-inverse."""
    rng = np.random.default_rng(14)
    b_mat = rng.standard_normal((30, 6))
    b_mat[:, 4] = 0.0
    gram = b_mat.T @ b_mat
    x = gram + np.diag([0.5, 0.2, 0.3, 0.1, 0.0, 0.4])
    assert cholesky(x) is None and cholesky(np.array([[1.0, np.nan], [np.nan, 1.0]])) is None
    var, resolution = inverse_diagonals(x, gram)
    pinv = np.linalg.pinv(x)
    np.testing.assert_allclose(var, np.diag(pinv), rtol=0, atol=1e-12)
    np.testing.assert_allclose(resolution, np.diag(pinv @ gram), rtol=0, atol=1e-12)
    assert resolution[4] == pytest.approx(0.0, abs=1e-12) and np.all(resolution[[0, 1, 2, 3, 5]] < 1 - 1e-3)


@pytest.mark.parametrize("layout", ["contiguous", "strided", "float64"])
def test_channel_prediction_is_the_product_with_each_channel(layout):
    """``channel_prediction`` (BLAS on L's ``(M, 3N)`` rows, the table in every third entry) is ``L_k f`` to
    float32 rounding, as the strided product of the channel's view was; for a non-contiguous L (read through
    its view) and a float64 one alike, and for a single row."""
    from mi_bivariate.solve.regularised import channel_prediction

    L = _lighting(200, 11)
    if layout == "strided":
        L = np.ascontiguousarray(np.concatenate([L, L], axis=1))[:, ::2]  # the same values, not C-contiguous
        assert not L.flags.c_contiguous
    elif layout == "float64":
        L = L.astype(np.float64)
    I = np.einsum("mnk,nk->mk", L.astype(np.float64), _truth(12).reshape(N, 3))
    f = np.random.default_rng(13).random(N)
    for rows in (slice(None), slice(0, 1)):
        data = prepare_data_term(L[rows], I[rows])
        for k in range(3):
            got = channel_prediction(data, k, f)
            exact = L[rows][:, :, k].astype(np.float64) @ f.astype(L.dtype).astype(np.float64)
            assert got.dtype == L.dtype and got.shape == exact.shape
            tol = 1e-6 if L.dtype == np.float32 else 1e-14
            np.testing.assert_allclose(got, exact, rtol=0, atol=tol * np.abs(exact).max())
            np.testing.assert_allclose(got, L[rows][:, :, k] @ f.astype(L.dtype), rtol=0,
                                       atol=2 * tol * np.abs(exact).max())


def test_solve_keeps_its_prediction_and_skips_residuals_only_when_asked():
    """Each pair's ``predicted`` is ``L f`` of its table (to float32 rounding) and its residual is that
    prediction's; the result's ``predicted`` takes each channel from its winner. ``residuals=False`` leaves
    the residuals NaN and no prediction, with the same tables, alphas and winners."""
    L = _lighting(150, 21)
    I = np.einsum("mnk,nk->mk", L.astype(np.float64), _truth(22).reshape(N, 3))
    I *= 1 + 0.05 * np.random.default_rng(23).standard_normal(I.shape)
    data = prepare_data_term(L, I)
    full = solve_prepared(data, _prior(), n_t=N_T, n_s=N_S)
    bare = solve_prepared(data, _prior(), n_t=N_T, n_s=N_S, residuals=False)
    for pair, sol in full.pairs.items():
        exact = np.einsum("mnk,nk->mk", L.astype(np.float64), sol.table.reshape(N, 3).astype(np.float64))
        np.testing.assert_allclose(sol.predicted, exact, rtol=0, atol=1e-6 * np.abs(exact).max())
        np.testing.assert_allclose(sol.relative_residual, np.linalg.norm(I - exact, axis=0) / np.linalg.norm(I, axis=0),
                                   rtol=1e-5)
        np.testing.assert_array_equal(bare.pairs[pair].table, sol.table)
        assert bare.pairs[pair].predicted is None and np.all(np.isnan(bare.pairs[pair].relative_residual))
    assert bare.winner == full.winner and np.array_equal(bare.alphas, full.alphas)
    assert bare.predicted is None and np.all(np.isnan(bare.relative_residual))
    for k, w in enumerate(full.winner):
        np.testing.assert_array_equal(full.predicted[:, k], full.pairs[w].predicted[:, k])


def test_solve_stages_skip_only_the_first_stages_residuals(monkeypatch):
    """With a basis prior the first stage's residuals (which nothing reads) are not computed, and the second
    stage's are; without one the only stage computes them."""
    from mi_bivariate.basis_prior import BasisPrior
    from mi_bivariate.solve import regularised, stages

    calls = []
    real = regularised.solve_prepared

    def spy(*args, **kwargs):
        calls.append(kwargs.get("residuals", True))
        return real(*args, **kwargs)

    monkeypatch.setattr(stages, "solve_prepared", spy)
    L = _lighting(150, 31)
    I = np.einsum("mnk,nk->mk", L.astype(np.float64), _truth(32).reshape(N, 3))
    data = prepare_data_term(L, I)
    rng = np.random.default_rng(33)
    basis = BasisPrior.learn({f"m{i}": rng.random((N_T, N_S, 3)) + 0.1 for i in range(12)}, components=3)
    result = stages.solve_stages(data, _prior(), None, basis)
    assert calls == [False, True] and result.predicted is not None and np.all(np.isfinite(result.relative_residual))
    calls.clear()
    alone = stages.solve_stages(data, _prior(), None, None)
    assert calls == [True] and alone.predicted is not None
