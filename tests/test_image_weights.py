"""Several images weighted by how well each one's table predicts the others (solve.cross_image_factors)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from mi_bivariate import solve
from mi_bivariate.prior import Prior, default_prior
from mi_bivariate.solve import CROSS_FLOOR, DEFAULT_PAIR_RULE, IMAGE_WEIGHTS, cross_image_factors, solve_stages

N_T = N_S = 8
N = N_T * N_S


def _lighting(seed: int, m: int = 300) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = rng.random((m, N)) ** 3 * (rng.random((m, N)) < 0.5)
    return (base[:, :, None] * np.array([1.0, 0.8, 0.6])).astype(np.float32)


def _truth() -> np.ndarray:
    t = np.linspace(0, 1, N_T)[:, None, None]
    return ((0.2 + 8.0 * np.exp(-(t / 0.25) ** 2)) * np.ones((1, N_S, 3))).reshape(N, 3)


def _images(bias: float = 0.4, noise: float = 0.0):
    """Three images under independent lights; images 0 and 1 follow the bivariate model, image 2
    carries a model error its own fit absorbs (its pixels follow a table whose peak is ``bias``
    higher, as a lighting-specific phi_d weighting would)."""
    rng = np.random.default_rng(3)
    f = _truth()
    t = np.repeat(np.linspace(0, 1, N_T), N_S)[:, None]
    f_seen = f * (1.0 + bias * np.exp(-(t / 0.25) ** 2))
    Ls, Is = [], []
    for k in range(3):
        L = _lighting(10 + k)
        I = np.einsum("mnc,nc->mc", L.astype(np.float64), f_seen if k == 2 else f)
        Ls.append(L)
        Is.append(I * (1.0 + noise * rng.standard_normal(I.shape)))
    return np.concatenate(Ls), np.concatenate(Is), np.repeat([0, 1, 2], len(Ls[0])), f


def test_the_image_the_others_do_not_confirm_counts_less():
    L, I, index, f = _images()
    prior = default_prior().resampled(N_T, N_S)
    sigma = solve.row_sigma(I, index)
    factors = cross_image_factors(L, I, index, sigma, prior, 1e-2)
    assert factors.shape == (3,) and factors.min() == 1.0 and factors[2] > 1.3 * factors[:2].max(), factors
    # ... and the weighted joint solve is closer to the truth than the equally weighted one.
    equal = solve_stages(solve.prepare_data_term(L, I, sigma), prior, 1e-2).table.reshape(-1, 3)
    weighted = solve_stages(solve.prepare_data_term(L, I, sigma * factors[index][:, None]), prior,
                            1e-2).table.reshape(-1, 3)
    assert np.linalg.norm(weighted - f) < 0.9 * np.linalg.norm(equal - f)


def test_factors_ignore_brightness_and_noise_and_need_two_images():
    L, I, index, _ = _images()
    prior = default_prior().resampled(N_T, N_S)
    sigma = solve.row_sigma(I, index)
    factors = cross_image_factors(L, I, index, sigma, prior, 1e-2)
    # Image 1 and its lighting 50x brighter: its sigma follows its own scale; nothing changes.
    L2, I2 = L.copy(), I.copy()
    L2[index == 1] *= 50.0
    I2[index == 1] *= 50.0
    brighter = cross_image_factors(L2, I2, index, solve.row_sigma(I2, index), prior, 1e-2)
    np.testing.assert_allclose(brighter, factors, rtol=1e-4)
    # Model-consistent images with 5% pixel noise: each image's own noise is discounted, factors near 1.
    L3, I3, _, _ = _images(bias=0.0, noise=0.05)
    same = cross_image_factors(L3, I3, index, solve.row_sigma(I3, index), prior, 1e-2)
    assert np.all(same < 1.3), same
    one = index == 0
    assert np.array_equal(cross_image_factors(L[one], I[one], index[one], sigma[one], prior, 1e-2), np.ones(1))


def test_recover_refuses_an_unknown_image_weighting():
    from mi_bivariate.errors import InputError
    from mi_bivariate.geometry import SphereGeometry
    from mi_bivariate.recover import recover
    from mi_bivariate.sources import synthetic_environment

    assert IMAGE_WEIGHTS == ("cross", "equal")
    with pytest.raises(InputError, match="image_weights"):
        recover(np.ones((16, 16, 3), np.float32), synthetic_environment(), SphereGeometry(8, 8, 6),
                image_weights="loudest")


def test_factors_follow_the_documented_formula():
    """A second implementation of the docstring's rule, on noisy images of three sizes (the degrees of
    freedom given back matter most for the smallest): d_ij^2 = max(||L_j f_i - I_j||^2 - s_j^2, 0) / ||I_j||^2
    with s_j^2 = sum_c RSS_jc M_j / (M_j - dof_jc), d_i the RMS over j != i, factors d / min d (>= 1)."""
    L, I, index, _ = _images(bias=0.3, noise=0.05)
    keep = np.concatenate([np.arange(300), 300 + np.arange(120), 600 + np.arange(200)])
    L, I, index = L[keep], I[keep], index[keep]
    prior = default_prior().resampled(N_T, N_S)
    sigma = solve.row_sigma(I, index)
    factors = cross_image_factors(L, I, index, sigma, prior, 1e-2)
    tables, own = [], []
    for i in range(3):
        rows = index == i
        result = solve_stages(solve.prepare_data_term(L[rows], I[rows], sigma[rows]), prior, 1e-2)
        table = result.table.reshape(-1, 3).astype(np.float32).astype(np.float64)
        dof = result.resolution.reshape(-1, 3).sum(axis=0)
        rss = np.sum((np.einsum("mnc,nc->mc", L[rows].astype(np.float64), table) - I[rows]) ** 2, axis=0)
        tables.append(table)
        own.append(float(np.sum(rss * rows.sum() / (rows.sum() - dof))))
    d = np.zeros(3)
    for i in range(3):
        excess = []
        for j in range(3):
            if j != i:
                rows = index == j
                rss = np.sum((np.einsum("mnc,nc->mc", L[rows].astype(np.float64), tables[i]) - I[rows]) ** 2)
                excess.append(max(rss - own[j], 0.0) / np.sum(I[rows] ** 2))
        d[i] = np.sqrt(np.mean(excess))
    expected = np.maximum(d / max(d.min(), 1e-3), 1.0)
    np.testing.assert_allclose(factors, expected, rtol=1e-5)
    assert factors[2] > 1.3


def test_images_that_agree_keep_their_weight():
    """Noise-free images of one table under different lights: every table predicts the others to
    rounding, no excess, every factor exactly 1 (never below: the factors only ever lower a weight)."""
    L, I, index, _ = _images(bias=0.0)
    prior = default_prior().resampled(N_T, N_S)
    factors = cross_image_factors(L, I, index, solve.row_sigma(I, index), prior, 1e-6)
    np.testing.assert_array_equal(factors, 1.0)


def _documented_factors(L, I, index, sigma, prior, alpha, pair_rule: str = DEFAULT_PAIR_RULE):
    """The docstring's rule written out (as in the test above), for any image indices: ``{image: factor}``."""
    images = np.unique(index)
    tables, own = {}, {}
    for i in images:
        rows = index == i
        result = solve_stages(solve.prepare_data_term(L[rows], I[rows], sigma[rows]), prior, alpha, pair_rule=pair_rule)
        tables[i] = result.table.reshape(-1, 3).astype(np.float32).astype(np.float64)
        dof = result.resolution.reshape(-1, 3).sum(axis=0)
        rss = np.sum((np.einsum("mnc,nc->mc", L[rows].astype(np.float64), tables[i]) - I[rows]) ** 2, axis=0)
        own[i] = float(np.sum(rss * rows.sum() / (rows.sum() - dof)))
    d = {}
    for i in images:
        excess = []
        for j in images[images != i]:
            rows = index == j
            rss = np.sum((np.einsum("mnc,nc->mc", L[rows].astype(np.float64), tables[i]) - I[rows]) ** 2)
            excess.append(max(rss - own[j], 0.0) / np.sum(I[rows] ** 2))
        d[i] = np.sqrt(np.mean(excess))
    low = max(min(d.values()), CROSS_FLOOR)
    return {i: max(d[i] / low, 1.0) for i in images}, d


def test_factors_divide_by_the_floor_when_one_table_predicts_the_others_exactly():
    """Two noise-free images of one table: image 0 lit from everywhere (its table is the truth and predicts
    image 1 to rounding, ``d_0`` far below :data:`CROSS_FLOOR`), image 1 lit from a few nodes (its table
    guesses the rest). Image 1's factor is ``d_1 / CROSS_FLOOR``, not ``d_1 / d_0``; image indices with a gap
    (0 and 2) give the image without rows a factor of 1 and the others their own."""
    f = _truth()
    rich = _lighting(20, 200)
    sparse = _lighting(21, 200) * (np.arange(N) % 4 == 0)[None, :, None]
    L = np.concatenate([rich, sparse])
    I = np.einsum("mnc,nc->mc", L.astype(np.float64), f)
    index = np.repeat([0, 2], 200)
    prior = default_prior().resampled(N_T, N_S)
    sigma = solve.row_sigma(I, index)
    factors = cross_image_factors(L, I, index, sigma, prior, 1e-6)
    expected, d = _documented_factors(L, I, index, sigma, prior, 1e-6)
    assert d[0] < 0.1 * CROSS_FLOOR < d[2], d
    assert factors.shape == (3,) and factors[1] == 1.0
    np.testing.assert_allclose(factors[[0, 2]], [expected[0], expected[2]], rtol=1e-5)
    assert factors[2] == pytest.approx(d[2] / CROSS_FLOOR, rel=1e-5)


def test_one_image_needs_no_cross_prediction():
    """One image (or an index naming only image 2): nothing to cross-predict, every factor 1, no solve and no
    warning (going on gave ``Mean of empty slice`` from the empty set of other images)."""
    L, I, index, _ = _images()
    prior = default_prior().resampled(N_T, N_S)
    two = index == 2
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        factors = cross_image_factors(L[two], I[two], index[two], solve.row_sigma(I[two]), prior, 1e-2)
    np.testing.assert_array_equal(factors, np.ones(3))


def test_factors_solve_each_image_with_the_pair_rule_given():
    """``pair_rule`` reaches each image's own solve: with a prior whose pairs differ node by node, the paper's
    residual rule keeps other pairs than the evidence in some image, and the factors are the documented rule's
    on those solves (they differ from the evidence rule's by ~2e-4, twenty times the tolerance)."""
    L, I, index, _ = _images(bias=0.3, noise=0.05)
    rng = np.random.default_rng(2)
    prior = Prior({p: (rng.uniform(0.2, 5.0, (N_T, N_S)), rng.uniform(0.2, 5.0, (N_T, N_S)))
                   for p in ("diffuse", "gloss")})
    sigma = solve.row_sigma(I, index)
    expected = np.array(list(_documented_factors(L, I, index, sigma, prior, 1e-2, "residual")[0].values()))
    evidence = np.array(list(_documented_factors(L, I, index, sigma, prior, 1e-2)[0].values()))
    assert np.abs(expected / evidence - 1).max() > 1e-4
    np.testing.assert_allclose(cross_image_factors(L, I, index, sigma, prior, 1e-2, pair_rule="residual"), expected,
                               rtol=1e-5)
