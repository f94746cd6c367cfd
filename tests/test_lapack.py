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


@pytest.mark.parametrize("order", ["C", "F"])
def test_trtri_inverts_the_factor_in_either_triangle(order):
    """The inverse Cholesky factor, against numpy's inverse of the same triangle: lower and upper
    factors, both memory orders, in place and not; X^-1 = W^T W (lower) or W W^T (upper)."""
    g = np.asarray(_spd(50, 7), order=order)
    inverse = np.linalg.inv(g)
    for lower in (True, False):
        c, low = sla.cho_factor(g, lower=lower)
        c = np.asarray(c, order=order)
        tri = np.tril if low else np.triu
        w = tri(lapack.trtri((c, low)))
        np.testing.assert_allclose(w, np.linalg.inv(tri(c)), rtol=1e-9, atol=1e-12 * np.abs(w).max())
        np.testing.assert_allclose(w.T @ w if low else w @ w.T, inverse, rtol=1e-9, atol=1e-12 * np.abs(inverse).max())
        kept = c.copy()
        if c.flags.c_contiguous or c.flags.f_contiguous:
            assert lapack.trtri((c, low), overwrite=True) is c  # the factor's memory took the inverse
            np.testing.assert_allclose(tri(c), w, rtol=1e-12, atol=1e-15 * np.abs(w).max())  # copy: C order
        assert lapack.trtri((kept, low)) is not kept
    assert lapack.trtri((np.zeros((0, 0)), True)).shape == (0, 0)
    with pytest.raises(np.linalg.LinAlgError):
        lapack.trtri((np.zeros((3, 3)), True))
    with pytest.raises(ValueError):
        lapack.trtri((np.ones((4, 3)), True))


def test_non_contiguous_empty_and_in_place():
    g = _spd(40, 5)
    b = np.random.default_rng(6).standard_normal(40)
    big = np.zeros((80, 80))
    big[::2, ::2] = np.linalg.cholesky(g)
    strided = (big[::2, ::2], True)  # a non-contiguous factor is copied, not misread
    np.testing.assert_allclose(lapack.cho_solve(strided, b), np.linalg.solve(g, b), rtol=1e-9)
    np.testing.assert_allclose(lapack.cho_solve(strided, np.ascontiguousarray(np.c_[b, b])[::1, :1])[:, 0],
                               np.linalg.solve(g, b), rtol=1e-9)
    empty = lapack.cho_factor(np.zeros((0, 0)))
    assert empty[0].shape == (0, 0) and lapack.potri(empty).shape == (0, 0)
    factor = lapack.cho_factor(g)
    expected = np.tril(lapack.potri(factor))
    inv = lapack.potri(factor, overwrite=True)
    assert inv is factor[0]  # the factor's memory took the inverse
    np.testing.assert_array_equal(np.tril(inv), expected)
    np.testing.assert_allclose(np.tril(inv), np.tril(np.linalg.inv(g)), rtol=1e-9, atol=1e-12)


def test_bad_shapes_raise_instead_of_reading_past_the_buffer():
    good = lapack.cho_factor(4.0 * np.eye(4))
    for bad_factor in ((np.ones((20, 3)), True), (np.full(30, 2.0), True), (np.eye(4)[:, :2], True)):
        with pytest.raises(ValueError):
            lapack.potri(bad_factor)
        with pytest.raises(ValueError):
            lapack.cho_solve(bad_factor, np.ones(bad_factor[0].shape[0]))
    for bad_rhs in (np.ones(5), np.ones((4, 2, 2)), np.ones((4, 2), complex)):
        with pytest.raises(ValueError):
            lapack.cho_solve(good, bad_rhs)
    with pytest.raises(ValueError):
        lapack.cho_factor(np.eye(3, dtype=complex))


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



def test_a_call_does_not_stall_other_python_threads():
    """The point of the module: while LAPACK runs, other Python threads run. scipy's wrappers hold
    the GIL for the whole call (a spinning thread stalled 57-130 ms during a 2000 x 2000 one);
    these stall it for a switch interval (~5 ms)."""
    import threading
    import time

    g = _spd(2000, 7)
    for attempt in range(3):  # a loaded machine may deschedule the spinner once
        done, gaps = threading.Event(), []

        def spin():
            last = time.perf_counter()
            while not done.is_set():
                now = time.perf_counter()
                gaps.append(now - last)
                last = now

        spinner = threading.Thread(target=spin)
        spinner.start()
        time.sleep(0.01)
        t0 = time.perf_counter()
        lapack.cho_factor(g)
        call = time.perf_counter() - t0
        done.set()
        spinner.join()
        if max(gaps) < 0.25 * call:
            return
    pytest.fail(f"a spinning thread stalled {max(gaps) * 1e3:.0f} ms during a {call * 1e3:.0f} ms factorisation")


def test_overwrite_never_writes_into_an_array_lapack_cannot_take_as_it_is():
    """``overwrite=True`` factorises in place only a writeable, contiguous, native float64 array: a read-only
    one, a float32 one and a big-endian one are copied (the input unchanged) and factorised right, as are
    such factors given to ``cho_solve``."""
    g = _spd(12, 4)
    b = np.random.default_rng(5).standard_normal(12)
    exact = np.linalg.cholesky(g)
    read_only = g.copy()
    read_only.flags.writeable = False
    for a in (read_only, g.astype(np.float32), g.astype(">f8")):
        kept = a.copy()
        c, lower = lapack.cho_factor(a, overwrite=True)
        assert c is not a and lower
        np.testing.assert_array_equal(a, kept)
        rtol = 1e-5 if a.dtype == np.float32 else 1e-12
        np.testing.assert_allclose(np.tril(c), np.linalg.cholesky(kept.astype(np.float64)), rtol=rtol, atol=rtol)
    for c in (exact.astype(np.float32), exact.astype(">f8")):
        factor = (c, True)
        want = np.linalg.solve(c.astype(np.float64) @ c.astype(np.float64).T, b)
        np.testing.assert_allclose(lapack.cho_solve(factor, b), want, rtol=1e-9)
        np.testing.assert_allclose(np.tril(lapack.potri(factor)), np.tril(np.linalg.inv(
            c.astype(np.float64) @ c.astype(np.float64).T)), rtol=1e-9, atol=1e-12)


def test_scipy_fallback_keeps_the_documented_factor_and_triangles(monkeypatch):
    """Without the GIL-free route (``GIL_FREE`` off: scipy's wrappers) the module keeps its contract:
    ``cho_factor`` hands back ``L`` in the lower triangle (``(c, True)``), and ``potri``, ``trtri`` work in
    the given factor's own triangle, lower or upper, against numpy's inverses."""
    monkeypatch.setattr(lapack, "GIL_FREE", False)
    g = _spd(30, 11)
    inverse = np.linalg.inv(g)
    c, lower = lapack.cho_factor(g)
    assert lower is True
    np.testing.assert_allclose(np.tril(c), np.linalg.cholesky(g), rtol=1e-12, atol=1e-12)
    for low in (True, False):
        f = sla.cho_factor(g, lower=low)
        tri = np.tril if low else np.triu
        np.testing.assert_allclose(tri(lapack.potri(f)), tri(inverse), rtol=1e-9, atol=1e-12 * np.abs(inverse).max())
        w = tri(lapack.trtri(f))
        np.testing.assert_allclose(w, np.linalg.inv(tri(f[0])), rtol=1e-9, atol=1e-12 * np.abs(w).max())


def test_cho_solve_of_empty_systems():
    """``cho_solve`` of a 0 x 0 factor (and of no right-hand sides) returns the empty answer of the right-hand
    side's shape, as numpy's ``solve`` does, instead of handing LAPACK a leading dimension of 0."""
    empty = lapack.cho_factor(np.zeros((0, 0)))
    for b in (np.zeros(0), np.zeros((0, 2))):
        assert lapack.cho_solve(empty, b).shape == np.linalg.solve(np.zeros((0, 0)), b).shape == b.shape
    assert lapack.cho_solve(lapack.cho_factor(_spd(3, 12)), np.zeros((3, 0))).shape == (3, 0)
