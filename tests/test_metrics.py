"""BRDF and image error metrics against hand-computed values and independent implementations."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mi_bivariate import analytic, metrics
from mi_bivariate.bivariate import BivariateBRDF, reduction_error, reduction_error_per_channel


def test_relative_rms_by_hand():
    truth = np.array([1.0, 2.0, 4.0, 0.0, 5.0])
    estimate = np.array([1.1, 1.8, 4.0, 7.0, 100.0])
    cells = np.array([True, True, True, True, False])     # zero truth and masked cell do not count
    assert metrics.relative_rms(truth, estimate, cells) == pytest.approx(math.sqrt(0.02 / 3), rel=1e-12)
    assert math.isnan(metrics.relative_rms(truth, estimate, np.zeros(5, bool)))
    # An estimate constant along an axis broadcasts (the bivariate case, constant in phi_d).
    assert metrics.relative_rms(np.array([[1.0, 2.0], [4.0, 8.0]]), np.array([[2.0], [4.0]]),
                                np.ones((2, 2), bool)) == pytest.approx(math.sqrt((1 + 0 + 0 + 0.25) / 4))


def test_weighted_relative_l2_by_hand():
    truth = np.array([1.0, 2.0, np.nan])
    estimate = np.array([2.0, 2.0, 3.0])
    weights = np.array([1.0, 3.0, 1.0])                    # the NaN truth cell is ignored
    assert metrics.weighted_relative_l2(truth, estimate, weights) == pytest.approx(math.sqrt(1.0 / 13.0))
    assert math.isnan(metrics.weighted_relative_l2(np.zeros(2), np.ones(2), np.ones(2)))


def test_log_rms_by_hand():
    e = math.e
    truth = np.array([0.0, e - 1.0, 1.0])
    estimate = np.array([e - 1.0, e - 1.0, -5.0])          # negative estimates clip to 0
    cells = np.array([True, True, False])
    assert metrics.log_rms(truth, estimate, cells) == pytest.approx(math.sqrt(0.5), rel=1e-12)
    assert metrics.log_rms(truth, estimate, np.ones(3, bool)) == pytest.approx(
        math.sqrt((1.0 + 0.0 + math.log(2.0) ** 2) / 3.0), rel=1e-12)


def test_merl_cell_weights_integrate_projected_solid_angle():
    # The integral of cos(theta_i) cos(theta_o) over both hemispheres is pi^2.
    w = metrics.merl_cell_weights()
    assert w.shape == (90, 90, 180)
    assert w.sum() == pytest.approx(math.pi ** 2, rel=2e-3)
    from mi_bivariate.merl import geometric_mask

    assert np.all(w[~geometric_mask()] == 0.0) and np.all(w >= 0.0)


@pytest.fixture(scope="module")
def lambertian_truth():
    return analytic.to_merl(analytic.Lambertian([0.5, 0.3, 0.2]))


def test_brdf_errors_closed_form_scaled_estimate(lambertian_truth):
    albedo = np.array([0.5, 0.3, 0.2])
    scaled = BivariateBRDF(np.broadcast_to(1.1 * albedo / math.pi, (8, 8, 3)))
    e = metrics.brdf_errors(lambertian_truth, scaled)
    # f_hat = 1.1 f everywhere: every relative measure is 0.1.
    assert e["eq1"] == pytest.approx(0.1, rel=1e-5)
    assert e["eq1_rgb"] == pytest.approx([0.1] * 3, rel=1e-5)
    assert e["cosine"] == pytest.approx(0.1, rel=1e-5)
    expected_log = math.sqrt(np.mean((np.log1p(1.1 * albedo / math.pi) - np.log1p(albedo / math.pi)) ** 2))
    assert e["log"] == pytest.approx(expected_log, rel=1e-5)
    # A 3D estimate identical to the truth has no error.
    e3 = metrics.brdf_errors(lambertian_truth, analytic.Lambertian([0.5, 0.3, 0.2]))
    assert e3["eq1"] < 1e-12 and e3["cosine"] < 1e-12 and e3["log"] < 1e-12


def test_eq1_matches_reduction_error():
    # Second implementation: bivariate.reduction_error (helper A's), on a non-bivariate BRDF.
    truth = analytic.to_merl(analytic.CookTorranceGGX([0.2, 0.1, 0.05], 0.6, alpha=0.15, ior=1.5))
    floor = BivariateBRDF.reduce(truth, n_t=16, n_s=16)
    e = metrics.brdf_errors(truth, floor)
    assert e["eq1"] == pytest.approx(reduction_error(truth, floor), rel=1e-9)
    assert e["eq1_rgb"] == pytest.approx(reduction_error_per_channel(truth, floor).tolist(), rel=1e-9)
    # The phi_d-averaged table's own MERL grid form gives the same numbers.
    assert metrics.brdf_errors(truth, floor.to_merl())["eq1"] == pytest.approx(e["eq1"], rel=1e-6)


def test_image_metrics_by_hand():
    ref = np.zeros((2, 2, 3))
    ref[0, 0] = 2.0
    ref[1, 1] = 1.0
    img = ref.copy()
    img[1, 1] = 1.5
    mask = np.array([[True, False], [False, True]])
    # Masked: 6 values, one differs by 0.5.
    assert metrics.image_relative_rmse(img, ref, mask) == pytest.approx(
        math.sqrt(0.25 * 3 / 6) / math.sqrt((4 * 3 + 1 * 3) / 6))
    assert metrics.image_psnr(img, ref, mask) == pytest.approx(10 * math.log10(4.0 / (0.25 * 3 / 6)))
    assert metrics.image_psnr(ref, ref) == math.inf
