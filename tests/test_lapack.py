"""mi_bivariate.solve.lapack: LAPACK's Cholesky routines without the GIL, against scipy and numpy."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla

from mi_bivariate.solve import lapack


def _spd(n: int, seed: int) -> np.ndarray:
    a = np.random.default_rng(seed).standard_normal((n + 20, n))
    return a.T @ a


def test_the_gil_free_route_is_in_use():
    # scipy has exported its Cython LAPACK since 0.16; without it the module falls back silently,
    # and this test is what says so.
    assert lapack.GIL_FREE


@pytest.mark.parametrize("order", ["C", "F"])
def test_factor_solve_and_inverse_match_scipy(order):
    g = np.asarray(_spd(60, 1), order=order)
    b = np.random.default_rng(2).standard_normal((60, 4))
    factor = lapack.cho_factor(g)
    assert factor[1] is True
    np.testing.assert_allclose(np.tril(factor[0]), np.linalg.cholesky(g), rtol=1e-12, atol=1e-12)
    assert np.array_equal(g, np.asarray(_spd(60, 1), order=order)), "the input was overwritten"
    exact = np.linalg.solve(g, b)
    inverse = np.linalg.inv(g)
    # Our factor and scipy's, in both triangles and both memory orders, through both solvers.
    factors = [factor, sla.cho_factor(g, lower=True), sla.cho_factor(g, lower=False),
               (np.ascontiguousarray(factor[0]), True), (np.asfortranarray(factor[0]), True)]
    for f in factors:
        np.testing.assert_allclose(lapack.cho_solve(f, b), exact, rtol=1e-9)
        np.testing.assert_allclose(lapack.cho_solve(f, b[:, 0]), exact[:, 0], rtol=1e-9)
        np.testing.assert_allclose(sla.cho_solve(f, b), exact, rtol=1e-9)
        tri = np.tril if f[1] else np.triu
        np.testing.assert_allclose(tri(lapack.potri(f)), tri(inverse), rtol=1e-9, atol=1e-12 * np.abs(inverse).max())


def test_overwrite_and_errors():
    g = _spd(30, 3)
    work = g.copy()
    c, _ = lapack.cho_factor(work, overwrite=True)
    assert c is work  # factorised in place
    with pytest.raises(np.linalg.LinAlgError):
        lapack.cho_factor(-g)
    semi = np.ones((5, 5))  # rank 1
    with pytest.raises(np.linalg.LinAlgError):
        lapack.cho_factor(semi)
    with pytest.raises(ValueError):
        lapack.cho_factor(np.ones((3, 4)))
    with pytest.raises(np.linalg.LinAlgError):
        lapack.potri((np.zeros((3, 3)), True))
    assert lapack.cho_solve(lapack.cho_factor(g), np.zeros((30, 0))).shape == (30, 0)

