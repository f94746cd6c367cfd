"""The parametric baselines against closed forms and second routes: the Ward lobe's formula and normalisation,
the phi_d average against ``BivariateBRDF.reduce``, the fit's reported residual and its per-channel weighting."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mi_bivariate import analytic, baselines
from mi_bivariate.bivariate import BivariateBRDF


def test_ward_lobe_closed_form_and_normalisation():
    """Ward (1992): ``kd / pi + ks exp(-tan^2 theta_h / a^2) / (4 pi a^2 sqrt(cos_i cos_o))``, written out here
    at a mirror pair and an off-specular one; the lobe reflects about all the light at normal view (its
    normalisation; 1 - O(a^2): 0.993 at a = 0.05, by midpoint quadrature over the hemisphere)."""
    a = 0.05
    model = baselines.WardIsotropic([0.2, 0.1, 0.0], [1.0, 2.0, 3.0], alpha=a)
    n = np.array([0.0, 0.0, 1.0])
    kd, ks = np.array([0.2, 0.1, 0.0]), np.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(model.eval_dirs(n, n), kd / math.pi + ks / (4 * math.pi * a * a), rtol=1e-12)
    wi = np.array([math.sin(0.5), 0.0, math.cos(0.5)])
    wo = np.array([-math.sin(0.3), 0.0, math.cos(0.3)])  # h tilted 0.1 rad from the normal
    lobe = math.exp(-math.tan(0.1) ** 2 / a ** 2) / (4 * math.pi * a * a * math.sqrt(math.cos(0.5) * math.cos(0.3)))
    np.testing.assert_allclose(model.eval_dirs(wi, wo), kd / math.pi + lobe * ks, rtol=1e-9)
    n_theta, n_phi = 4000, 16
    theta = (np.arange(n_theta) + 0.5) * (0.5 * math.pi / n_theta)
    phi = (np.arange(n_phi) + 0.5) * (2 * math.pi / n_phi)
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    dirs = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3)
    dw = (np.sin(th) * (0.5 * math.pi / n_theta) * (2 * math.pi / n_phi)).reshape(-1)
    unit = baselines.WardIsotropic(0.0, 1.0, alpha=a)
    albedo = np.sum(unit.eval_dirs(dirs, np.broadcast_to(n, dirs.shape))[:, 0] * dirs[:, 2] * dw)
    assert albedo == pytest.approx(1.0, abs=0.01)


def test_phi_averager_matches_reduce_for_a_broad_lobe():
    """A broad GGX lobe is still bright near the grazing nodes, where the phi_d average depends on the clamp of
    the last node to 89/90 (as ``BivariateBRDF.reduce`` clamps): the averager's table is reduce's."""
    model = analytic.CookTorranceGGX([0.1, 0.2, 0.3], 1.0, alpha=0.9, ior=1.5)
    table = baselines.PhiAverager(6, 7, n_phi=20).average(model)
    np.testing.assert_allclose(table, BivariateBRDF.reduce(model, n_t=6, n_s=7, n_phi=20).table, rtol=1e-5)


@pytest.fixture(scope="module")
def two_lobe_data():
    """Observations of a material no single GGX fits (channel 0 alpha = 0.08, channels 1, 2 alpha = 0.4),
    through a sparse random lighting matrix on a 10 x 10 grid."""
    averager = baselines.PhiAverager(10, 10)
    sharp = averager.average(analytic.CookTorranceGGX([0.2, 0.2, 0.2], 0.5, alpha=0.08, ior=1.5))
    broad = averager.average(analytic.CookTorranceGGX([0.2, 0.2, 0.2], 0.5, alpha=0.4, ior=1.5))
    table = np.concatenate([sharp[..., :1], broad[..., 1:]], axis=-1).reshape(-1, 3)
    rng = np.random.default_rng(1)
    L = (rng.random((600, 100, 3)) * (rng.random((600, 100, 1)) < 0.15)).astype(np.float32)
    return averager, L, np.einsum("mnc,nc->mc", L.astype(np.float64), table)


def test_fit_reports_its_residual_through_the_lighting_matrix(two_lobe_data):
    """``relative_residual`` is ``||I - L f|| / ||I||`` of the fitted model's table, recomputed here from the
    fit's own table; and that table is the fitted 3D model's phi_d average (``BivariateBRDF.reduce`` at the
    averager's 45 phi_d)."""
    averager, L, I = two_lobe_data
    fit = baselines.fit_baseline("ggx", L, I, grid=(10, 10), averager=averager, max_nfev=10, starts=2)
    pred = np.einsum("mnc,nc->mc", L.astype(np.float64), fit.table.table.reshape(-1, 3))
    want = np.linalg.norm(pred - I) / np.linalg.norm(I)
    assert want > 0.01                                     # a real misfit: the two channels disagree on alpha
    assert fit.relative_residual == pytest.approx(want, rel=1e-4)
    np.testing.assert_allclose(fit.table.table, BivariateBRDF.reduce(fit.brdf, n_t=10, n_s=10, n_phi=45).table,
                               rtol=1e-5)


def test_fit_weighs_the_channels_alike(two_lobe_data):
    """Residuals are relative per channel, so scaling one channel's observations (a brighter red) scales its
    kd and ks and leaves the shared lobe shape alone: an absolute residual would let the bright channel
    decide alpha."""
    averager, L, I = two_lobe_data
    kwargs = dict(grid=(10, 10), averager=averager, max_nfev=10, starts=2)
    base = baselines.fit_baseline("ggx", L, I, **kwargs)
    scaled = baselines.fit_baseline("ggx", L, I * np.array([100.0, 1.0, 1.0]), **kwargs)
    assert scaled.params["alpha"] == pytest.approx(base.params["alpha"], rel=1e-3)
    assert np.asarray(scaled.params["kd"]) == pytest.approx(np.asarray(base.params["kd"]) * [100.0, 1.0, 1.0],
                                                            rel=1e-3)


def test_fit_baselines_fits_each_family_and_refuses_non_finite_observations(two_lobe_data):
    """Each family named gets its own model (``fit_baselines`` shares only the direction tables); observations
    with a NaN are refused with the file-less InputError the evaluation reports, not fitted."""
    from mi_bivariate.errors import InputError

    averager, L, I = two_lobe_data
    fits = baselines.fit_baselines(L, I, grid=(10, 10), families=("ward", "ggx"), max_nfev=1, start_nfev=1, starts=1)
    assert [fits[f].family for f in ("ward", "ggx")] == ["ward", "ggx"]
    assert isinstance(fits["ward"].brdf, baselines.WardIsotropic)
    assert isinstance(fits["ggx"].brdf, analytic.CookTorranceGGX)
    bad = I.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InputError, match="non-finite"):
        baselines.fit_baseline("ggx", L, bad, grid=(10, 10), averager=averager)


def test_fit_recovers_the_parameters_of_a_model_in_its_family(two_lobe_data):
    """Observations made (through the fixture's lighting matrix) by a Lambertian + GGX model are fitted by that
    model: the fit returns its diffuse albedo, specular scale, roughness and index of refraction, each under
    its own name, and a residual of ~0."""
    averager, L, _ = two_lobe_data
    truth = analytic.CookTorranceGGX([0.2, 0.1, 0.05], [0.5, 0.6, 0.7], alpha=0.15, ior=1.5)
    I = np.einsum("mnc,nc->mc", L.astype(np.float64), averager.average(truth).reshape(-1, 3))
    fit = baselines.fit_baseline("ggx", L, I, grid=(10, 10), averager=averager, max_nfev=10, starts=2)
    np.testing.assert_allclose(fit.params["kd"], [0.2, 0.1, 0.05], rtol=1e-3)
    np.testing.assert_allclose(fit.params["ks"], [0.5, 0.6, 0.7], rtol=1e-3)
    assert fit.params["alpha"] == pytest.approx(0.15, rel=1e-3)
    assert fit.params["ior"] == pytest.approx(1.5, rel=1e-3)
    assert fit.relative_residual < 1e-5
    assert isinstance(fit.brdf, analytic.CookTorranceGGX) and fit.brdf.ior == pytest.approx(1.5, rel=1e-3)


def test_phi_average_leaves_out_non_finite_samples_and_fit_baselines_defaults_match():
    """A model that is NaN at some phi_d samples is averaged over its finite ones (as ``BivariateBRDF.reduce``
    does), not diluted by the missing ones; ``fit_baselines`` tabulates with ``fit_baseline``'s default 45
    phi_d, so both give the same fit; a lighting matrix for another grid is refused by name."""
    from mi_bivariate.errors import InputError

    class HalfMissing:
        name = "half-missing"

        def eval_dirs(self, wi, wo):
            return np.where((wi[..., 1] > 0.0)[..., None], np.nan, np.array([1.0, 2.0, 3.0]))

    table = baselines.PhiAverager(4, 5, n_phi=12).average(HalfMissing())
    np.testing.assert_allclose(table, np.broadcast_to([1.0, 2.0, 3.0], (4, 5, 3)), rtol=1e-12)

    averager = baselines.PhiAverager(6, 6)
    rng = np.random.default_rng(4)
    L = (rng.random((200, 36, 3)) * (rng.random((200, 36, 1)) < 0.3)).astype(np.float32)
    model = analytic.CookTorranceGGX([0.2, 0.2, 0.2], 0.5, alpha=0.3, ior=1.5)
    I = np.einsum("mnc,nc->mc", L.astype(np.float64), averager.average(model).reshape(-1, 3))
    kwargs = dict(max_nfev=1, start_nfev=1, starts=1)
    one = baselines.fit_baseline("ward", L, I, grid=(6, 6), **kwargs)
    both = baselines.fit_baselines(L, I, grid=(6, 6), families=("ward",), **kwargs)
    np.testing.assert_array_equal(both["ward"].table.table, one.table.table)
    with pytest.raises(InputError, match=r"lighting matrix: expected shape \(M, 36, 3\)"):
        baselines.fit_baseline("ward", L[:, :35], I, grid=(6, 6), **kwargs)


def test_ward_fit_recovers_a_ward_model(two_lobe_data):
    """As test_fit_recovers_the_parameters_of_a_model_in_its_family, for the Ward family. The 10 x 10 grid has a
    node exactly on the horizon's edge (theta_h = 10, theta_d = 80 degrees: wi on the horizon at phi_d = 0), whose
    rounding (+8e-17) once counted as above it: Ward's phi_d mean there was 1.8e6 1/sr, that one cell decided the
    fit, and it returned kd = 0 and alpha 0.10 for this alpha 0.15 model."""
    averager, L, _ = two_lobe_data
    truth = baselines.WardIsotropic([0.2, 0.1, 0.05], [0.5, 0.6, 0.7], alpha=0.15)
    table = averager.average(truth)
    assert table.max() < 1e3  # grazing cells reach 240 1/sr
    I = np.einsum("mnc,nc->mc", L.astype(np.float64), table.reshape(-1, 3))
    fit = baselines.fit_baseline("ward", L, I, grid=(10, 10), averager=averager, max_nfev=10, starts=2)
    np.testing.assert_allclose(fit.params["kd"], [0.2, 0.1, 0.05], rtol=1e-3)
    np.testing.assert_allclose(fit.params["ks"], [0.5, 0.6, 0.7], rtol=1e-3)
    assert fit.params["alpha"] == pytest.approx(0.15, rel=1e-3)
    assert fit.relative_residual < 1e-5
