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


# ------------------------------------------------ where the image looks (issue 8)

def _merl_angles_deg():
    n = np.arange(90)
    return (n / 90.0) ** 2 * 90.0, n / 90.0 * 90.0          # theta_h, theta_d of the MERL nodes (degrees)


def test_region_of_by_hand():
    deg = math.radians
    theta_h = np.array([deg(1.0), deg(1.0), deg(30.0), deg(30.0), deg(30.0), deg(2.0)])
    theta_d = np.array([deg(5.0), deg(80.0), deg(5.0), deg(80.0), deg(40.0), deg(40.0)])
    names = [metrics.REGION_NAMES[k] for k in metrics.region_of(theta_h, theta_d)]
    # Specular wins over retro and grazing; 2 degrees is already outside the specular region.
    assert names == ["specular", "specular", "retro", "grazing", "rest", "rest"]


def test_observed_cells_by_hand():
    nodes = np.ones((3, 3), bool)
    nodes[0, 0] = False                                    # node (t = 0, s = 0) unobserved
    cells = metrics.observed_cells(nodes)
    # MERL node i has t = i / 90 (and s = j / 90); a 3-node axis has nodes at 0, 1/2, 1. Cells with
    # t < 1/2 and s < 1/2 use node (0, 0) in their stencil; t = 1/2 (i = 45) sits on node 1 alone.
    expected = np.ones((90, 90), bool)
    expected[:45, :45] = False
    np.testing.assert_array_equal(cells, expected)
    assert metrics.observed_cells(np.ones((2, 2), bool)).all()
    assert not metrics.observed_cells(np.zeros((4, 5), bool)).any()


def test_region_breakdown_and_observed_eq1_by_hand(lambertian_truth):
    from mi_bivariate.merl import MERLBRDF, geometric_mask

    th_deg, _ = _merl_angles_deg()
    spec = th_deg < 2.0                                    # MERL theta_h rows in the specular region
    table = np.array(lambertian_truth.table, np.float64)
    table[spec] *= 2.0                                     # truth doubled there: relative error 0.5
    truth = MERLBRDF(table, name="doubled peak")
    estimate = BivariateBRDF(np.broadcast_to(np.array([0.5, 0.3, 0.2]) / math.pi, (8, 8, 3)))
    valid = geometric_mask()
    n_spec = int(valid[spec].sum()) * 3
    n_all = int(valid.sum()) * 3
    e = metrics.brdf_errors(truth, estimate, observed_nodes=np.ones((8, 8), bool))
    assert e["regions"]["specular"]["eq1"] == pytest.approx(0.5, rel=1e-6)
    assert e["regions"]["specular"]["cells"] == n_spec
    assert e["regions"]["specular"]["share"] == pytest.approx(1.0)
    for name in ("retro", "grazing", "rest"):
        assert e["regions"][name]["eq1"] == pytest.approx(0.0, abs=1e-6)
        assert e["regions"][name]["share"] == pytest.approx(0.0, abs=1e-9)
    assert sum(r["cells"] for r in e["regions"].values()) == n_all
    assert e["eq1"] == pytest.approx(0.5 * math.sqrt(n_spec / n_all), rel=1e-6)
    # Every node observed: the observed-cell Eq. 1 is Eq. 1.
    assert e["eq1_observed"] == pytest.approx(e["eq1"], rel=1e-9) and e["observed_fraction"] == 1.0
    # Unobserve the t = 0 row of nodes: the cells with t = i / 90 < 1/7 drop out. The specular
    # region ends at t = sqrt(2 / 90) = 0.149, so only its MERL row i = 13 (t = 0.144) stays.
    nodes = np.ones((8, 8), bool)
    nodes[0, :] = False
    e2 = metrics.brdf_errors(truth, estimate, observed_nodes=nodes)
    t_rows = np.arange(90) / 90.0
    kept = t_rows >= 1.0 / 7.0
    n_obs = int(valid[kept].sum()) * 3
    n_spec_obs = int(valid[kept & spec].sum()) * 3
    assert n_spec_obs == int(valid[13].sum()) * 3
    assert e2["eq1_observed"] == pytest.approx(0.5 * math.sqrt(n_spec_obs / n_obs), rel=1e-6)
    assert e2["observed_fraction"] == pytest.approx(valid[kept].sum() / valid.sum(), rel=1e-9)


def test_node_observation_strength_by_hand():
    from mi_bivariate import adequacy

    L = np.array([[1.0, 1.0, 0.0, 0.0],
                  [3.0, 1.0, 0.0, 0.0],
                  [0.0, 0.0, 0.0, 2.0]])                   # one channel, 3 rows, 2 x 2 nodes
    effective, signal = adequacy.node_observation_strength(L, 2, 2)
    # Shares: row 0 (0.5, 0.5), row 1 (0.75, 0.25), row 2 (0, 0, 0, 1).
    np.testing.assert_allclose(signal, [[1.25, 0.75], [0.0, 1.0]])
    np.testing.assert_allclose(effective, [[1.25 ** 2 / (0.25 + 0.5625), 0.75 ** 2 / (0.25 + 0.0625)],
                                           [0.0, 1.0]])
    np.testing.assert_array_equal(adequacy.observed_nodes(L, 2, 2, min_effective=1.5, min_signal=0.5),
                                  [[True, True], [False, False]])


def test_relight_errors_by_hand():
    truth = np.ones((2, 2, 3))
    mask = np.ones((2, 2), bool)
    r = metrics.relight_errors(1.1 * truth, 1.05 * truth, truth, mask)
    assert r["rel_rmse"] == pytest.approx(0.1) and r["floor"] == pytest.approx(0.05)
    assert r["ratio"] == pytest.approx(2.0)
    # a floor below the references' noise gives no ratio (it would divide by that noise)
    tiny = metrics.relight_errors(1.1 * truth, (1 + 0.5 * metrics.MIN_RELIGHT_FLOOR) * truth, truth, mask)
    assert math.isnan(tiny["ratio"]) and tiny["rel_rmse"] == pytest.approx(0.1)
    # ... and so does a floor below twice the reference's own measured noise (--quick's references: 5.7e-3)
    for noise, ratio in ((0.02, 2.0), (0.024, 2.0), (0.026, math.nan)):  # the floor is 0.05
        got = metrics.relight_errors(1.1 * truth, 1.05 * truth, truth, mask, reference_noise=noise)["ratio"]
        assert (math.isnan(got) and math.isnan(ratio)) or got == pytest.approx(ratio), (noise, got)


def test_psnr_peak_is_the_references():
    ref = np.zeros((2, 2, 3))
    ref[0, 0] = 2.0
    img = ref.copy()
    img[1, 1] = 3.0  # the estimate's own maximum is above the reference's
    assert metrics.image_psnr(img, ref) == pytest.approx(10 * math.log10(4.0 / (9.0 * 3 / 12)))


def test_eq1_min_leaves_out_the_cells_below_1e_3(lambertian_truth):
    """An estimate wrong only where the truth is below 1e-3 1/sr: Eq. 1 sees it, ``eq1_min`` does not."""
    from mi_bivariate.merl import MERLBRDF

    table = np.array(lambertian_truth.table, np.float64)
    dim = np.zeros(table.shape[:3], bool)
    dim[:, :, :90] = True
    table[dim] *= 1e-4  # ~1.6e-5 to 4e-5 1/sr there
    truth = MERLBRDF(table, name="half dim")
    estimate = table.copy()
    estimate[dim] *= 2.0
    e = metrics.brdf_errors(truth, estimate)
    assert e["eq1"] > 0.1 and e["eq1_min"] == pytest.approx(0.0, abs=1e-12)


def test_an_unobserved_interior_node_unobserves_the_cells_around_it():
    """A cell is observed only when all four nodes of its bilinear stencil are: unobserving node (1, 1)
    of a 3 x 3 grid drops every cell with t or s strictly between the first and last node from it."""
    from mi_bivariate.coordinates import half_diff_from_st

    nodes = np.ones((3, 3), bool)
    nodes[1, 1] = False
    s = np.array([0.0, 0.2, 0.5, 0.7, 1.0, 0.2, 0.7, 0.0, 1.0])
    t = np.array([0.0, 0.3, 0.5, 0.8, 1.0, 0.8, 0.3, 0.5, 0.5])
    theta_h, theta_d = half_diff_from_st(s, t)
    want = (s <= 0.0) | (s >= 1.0) | (t <= 0.0) | (t >= 1.0)  # off the four cells around node (1, 1)
    np.testing.assert_array_equal(metrics.observed_cells(nodes, theta_h, theta_d), want)


# ------------------------------------------------ mutation review: guards and second routes

def test_image_metrics_refuse_bad_masks_and_a_black_reference_is_no_perfect_score():
    """A 0/1 integer mask would index rows 0 and 1 (numpy's fancy indexing) and score the wrong pixels, a
    mask of another shape or one selecting no pixel has no number: all three are refused. Against a black
    reference the relative error is infinite (0 would read as a perfect relight) and the PSNR -inf."""
    ref = np.ones((4, 4, 3))
    img = 1.5 * ref
    img[0] = 9.0                                           # rows 0 and 1 differ from the lit square below
    as_int = np.zeros((4, 4), np.uint8)
    as_int[2:, 2:] = 1
    for bad in (as_int, np.ones((3, 4), bool), np.zeros((4, 4), bool)):
        for metric in (metrics.image_relative_rmse, metrics.image_psnr):
            with pytest.raises(ValueError):
                metric(img, ref, bad)
    with pytest.raises(ValueError):
        metrics.image_relative_rmse(img, ref[:3])
    assert metrics.image_relative_rmse(img, np.zeros_like(ref)) == math.inf
    assert metrics.image_psnr(img, np.zeros_like(ref)) == -math.inf


def test_seed_noise_by_hand():
    """Two renders of independent seeds differ by sqrt 2 times one render's noise, relative to the first."""
    a = np.full((2, 2, 3), 2.0)
    b = a.copy()
    b[0, 0] = 2.4                                          # one pixel of four off by 0.4 (20 %)
    # RMS difference sqrt(0.16 / 4) = 0.2 over the first image's RMS 2: 0.1, over sqrt 2.
    assert metrics.seed_noise(a, b) == pytest.approx(0.1 / math.sqrt(2.0), rel=1e-12)


def test_log_rms_leaves_out_missing_truth():
    """A NaN truth (a below-horizon MERL value) is no cell of the log error, as of Eq. 1."""
    truth = np.array([math.e - 1.0, np.nan])
    assert metrics.log_rms(truth, np.array([0.0, 1.0]), np.ones(2, bool)) == pytest.approx(1.0, rel=1e-12)


def test_merl_cell_weights_integrate_cosine_moments():
    """The weights spread the measure ``cos(theta_i) cos(theta_o) dw_i dw_o`` over (theta_h, theta_d, phi_d)
    as the closed forms say: int (cos_i + cos_o) cos_i cos_o = 2 (2 pi / 3) pi and int cos_i^2 cos_o^2 =
    (2 pi / 3)^2 over both hemispheres (cos_i, cos_o of each node written out here, phi_h = 0)."""
    from mi_bivariate.merl import node_angles

    w = metrics.merl_cell_weights()
    theta_h, theta_d, phi_d = np.meshgrid(*node_angles(), indexing="ij")
    wi_z = np.cos(theta_d) * np.cos(theta_h) - np.sin(theta_d) * np.sin(theta_h) * np.cos(phi_d)
    wo_z = np.cos(theta_d) * np.cos(theta_h) + np.sin(theta_d) * np.sin(theta_h) * np.cos(phi_d)
    assert np.sum(w * (wi_z + wo_z)) == pytest.approx(4.0 * math.pi ** 2 / 3.0, rel=2e-3)
    assert np.sum(w * wi_z * wo_z) == pytest.approx(4.0 * math.pi ** 2 / 9.0, rel=2e-3)


def test_a_bivariate_array_estimate_is_read_as_theta_h_by_theta_d():
    """An estimate given as a ``(90, 90, 3)`` array (the exact phi_d average, as the evaluation scores it) holds
    theta_h along its first axis and theta_d along its second, MERL's nodes (theta_h = 90 deg (i / 90)^2,
    theta_d = 90 deg j / 90), and is constant along phi_d."""
    from mi_bivariate.merl import node_angles

    i, j = np.meshgrid(np.arange(90), np.arange(90), indexing="ij")
    theta_h, theta_d = np.radians(90.0 * (i / 90.0) ** 2), np.radians(90.0 * j / 90.0)
    merl_h, merl_d, _ = node_angles()
    np.testing.assert_allclose(theta_h[:, 0], merl_h, rtol=1e-12)
    np.testing.assert_allclose(theta_d[0], merl_d, rtol=1e-12)
    values = np.stack([theta_h, theta_d, theta_h + 2.0 * theta_d], axis=-1)
    grid = metrics.estimate_on_merl_grid(values)
    assert grid.shape == (90, 90, 1, 3) and grid.dtype == np.float64
    np.testing.assert_array_equal(grid[:, :, 0], values)
    with pytest.raises(ValueError):
        metrics.estimate_on_merl_grid(values[:, :45])


def test_a_cell_on_a_node_row_needs_only_that_row():
    """A cell whose t sits exactly on a node row uses that row alone, not the next: unobserving the last row of a
    3 x 3 grid (t = 1) keeps every cell with t = i / 90 <= 1/2 (rows i <= 45) observed and drops the others."""
    nodes = np.ones((3, 3), bool)
    nodes[2, :] = False
    expected = np.zeros((90, 90), bool)
    expected[:46] = True
    np.testing.assert_array_equal(metrics.observed_cells(nodes), expected)


def test_relight_errors_noise_rule_and_psnr_by_hand():
    """The ratio needs a floor of at least the larger of MIN_RELIGHT_FLOOR and twice the reference's noise (not
    their sum), and the PSNR is the recovery's, not the floor's: 10 log10(peak^2 / mse) with peak 1, mse 0.01."""
    truth = np.ones((2, 2, 3))
    mask = np.ones((2, 2), bool)
    got = metrics.relight_errors(1.1 * truth, 1.05 * truth, truth, mask, reference_noise=0.0245)
    assert got["ratio"] == pytest.approx(2.0)              # 2 x 0.0245 = 0.049 <= 0.05 < 0.049 + 0.002
    assert got["psnr"] == pytest.approx(20.0)


def test_cosine_error_weighs_each_cell_by_its_projected_solid_angle(lambertian_truth):
    """A relative error that varies over the cells (50 % at theta_d >= 45 deg, 20 % more at theta_h rows
    i >= 60, none elsewhere): ``cosine`` is sqrt(sum w (f_hat - f)^2 / sum w f^2) written out here over the
    full (90, 90, 180) grid with the weights of :func:`merl_cell_weights`, not the unweighted share of cells
    (a uniform error, as in the scaled-estimate test, cancels the weights)."""
    f = np.array(lambertian_truth.table, np.float64)
    i, j = np.meshgrid(np.arange(90), np.arange(90), indexing="ij")
    rel = (0.5 * (j >= 45) + 0.2 * (i >= 60))[:, :, None]
    estimate = np.array([0.5, 0.3, 0.2]) / math.pi * (1.0 + rel)          # (90, 90, 3): constant along phi_d
    e = metrics.brdf_errors(lambertian_truth, estimate)
    w = np.broadcast_to(metrics.merl_cell_weights()[..., None], f.shape)
    valid = np.isfinite(f) & (w > 0)
    diff = estimate[:, :, None, :] - f
    want = math.sqrt(np.sum((w * diff ** 2)[valid]) / np.sum((w * f ** 2)[valid]))
    assert e["cosine"] == pytest.approx(want, rel=1e-9)
    unweighted = math.sqrt(np.sum((diff ** 2)[valid]) / np.sum((f ** 2)[valid]))
    assert abs(want - unweighted) > 0.02, (want, unweighted)    # the weights decide the number


def test_log_error_counts_every_cell_even_where_the_truth_is_zero(lambertian_truth):
    """Eq. 1 leaves out the cells whose truth is 0 (its relative error is undefined there); the log error,
    defined everywhere, counts every cell. An estimate wrong only where the truth is exactly 0 (0.1 1/sr there):
    Eq. 1 is 0, the log error is ln(1.1) times the root share of such cells."""
    from mi_bivariate.merl import MERLBRDF

    table = np.array(lambertian_truth.table, np.float64)
    table[:20] = np.where(np.isfinite(table[:20]), 0.0, np.nan)            # theta_h rows 0..19 exactly 0
    truth = MERLBRDF(table, name="zero at the peak")
    estimate = np.broadcast_to(np.array([0.5, 0.3, 0.2]) / math.pi, (90, 90, 3)).copy()
    estimate[:20] = 0.1
    valid = np.isfinite(table)
    share = valid[:20].sum() / valid.sum()
    assert 0.05 < share < 0.5
    e = metrics.brdf_errors(truth, estimate)
    assert e["eq1"] == pytest.approx(0.0, abs=1e-12) and e["eq1_min"] == pytest.approx(0.0, abs=1e-12)
    assert e["log"] == pytest.approx(math.log(1.1) * math.sqrt(share), rel=1e-9)
