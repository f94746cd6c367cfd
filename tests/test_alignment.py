"""Probe alignment: the yaw about world y that best explains an image of a known sphere."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import sky_probe

from mi_bivariate import alignment
from mi_bivariate.analytic import BivariateLobe
from mi_bivariate.bivariate import BivariateBRDF
from mi_bivariate.errors import InputError
from mi_bivariate.render import render_sphere


@pytest.fixture(scope="module")
def turned_render():
    """A sphere (material unknown to the estimator) under the sky probe turned by +25 degrees."""
    probe = sky_probe(n_lights=12)
    brdf = BivariateBRDF.reduce(BivariateLobe(diffuse=(0.3, 0.2, 0.1), specular=2.0, width=0.2))
    render = render_sphere(brdf, probe.rotated(euler_deg=(0, 25, 0)), resolution=80, spp=128, seed=3)
    return probe, brdf, render


def test_recovers_a_known_yaw(turned_render):
    probe, _, render = turned_render
    est = alignment.estimate_yaw(render.image, probe, render.geometry, n_normals=800, coarse_step_deg=20.0)
    assert abs(est.yaw_deg - 25.0) < 2.0, est.summary()
    # The residual curve: its minimum is the estimate, far-off yaws explain the image worse.
    assert est.residual <= est.residuals.min() + 1e-9
    assert est.residuals.max() > 2.0 * est.residual
    assert np.all(np.diff(est.angles_deg) > 0) and est.angles_deg.min() >= -180.0
    # The aligned probe is the captured one turned by the estimate.
    d = np.array([[0.3, 0.5, 0.8]])
    assert np.allclose(est.probe.eval(d), probe.rotated(euler_deg=(0, est.yaw_deg, 0)).eval(d))


def test_known_material_and_search_interval(turned_render):
    """With the material roughly known (scale free per channel) a small interval search suffices."""
    probe, brdf, render = turned_render
    start = probe.rotated(euler_deg=(0, 20, 0))  # a probe already close: 5 degrees left
    est = alignment.estimate_yaw(render.image, start, render.geometry, brdf=BivariateBRDF(0.5 * brdf.table),
                                 n_normals=800, grid=(32, 32), search_deg=(-15.0, 15.0), coarse_step_deg=5.0)
    assert abs(est.yaw_deg - 5.0) < 2.0, est.summary()
    with pytest.raises(InputError):
        alignment.estimate_yaw(render.image, probe, render.geometry, search_deg=(10.0, -10.0))


def test_search_interval_is_kept_and_the_estimate_wrapped(turned_render):
    """The estimate stays inside ``search_deg`` even when the best yaw lies beyond it (the truth, 25
    degrees, is outside (-15, 15): the estimate is the interval's end), and is reported in (-180, 180]
    when the interval crosses 180 degrees (the probe given turned by -170: the truth is 195 = -165)."""
    probe, brdf, render = turned_render
    known = dict(brdf=BivariateBRDF(0.5 * brdf.table), n_normals=400, grid=(16, 16), coarse_step_deg=5.0)
    est = alignment.estimate_yaw(render.image, probe, render.geometry, search_deg=(-15.0, 15.0), **known)
    assert 14.0 <= est.yaw_deg <= 15.0, est.summary()
    assert est.angles_deg.min() >= -15.0 and est.angles_deg.max() <= 15.0
    est = alignment.estimate_yaw(render.image, probe.rotated(euler_deg=(0, -170, 0)), render.geometry,
                                 search_deg=(175.0, 215.0), **known)
    assert abs(est.yaw_deg - (-165.0)) < 2.0, est.summary()


def test_the_residual_is_relative_and_the_yaw_in_the_half_open_turn(turned_render):
    """The residual is relative, ||I - L f|| / ||I||, and the known material has a free scale per channel: the
    image 1000x brighter (another exposure) with the material's channels scaled by (0.5, 1, 2) (another albedo)
    gives the same estimate, residual and curve. A yaw is reported in (-180, 180]: -180 as 180, a turn and a
    half as 180, -190 as 170."""
    probe, brdf, render = turned_render
    known = dict(n_normals=400, grid=(8, 8), search_deg=(18.0, 30.0), coarse_step_deg=4.0, tol_deg=0.5)
    est = alignment.estimate_yaw(render.image, probe, render.geometry, brdf=brdf, **known)
    other = alignment.estimate_yaw(1000.0 * render.image, probe, render.geometry,
                                   brdf=BivariateBRDF(brdf.table * np.array([0.5, 1.0, 2.0])), **known)
    assert 0.0 < est.residual < 0.5 and abs(est.yaw_deg - 25.0) < 2.0, est.summary()
    assert est.residual == est.residuals.min() < est.residuals[np.isin(est.angles_deg, [18.0, 22.0, 26.0, 30.0])].min()
    assert other.yaw_deg == pytest.approx(est.yaw_deg, abs=1e-6)
    np.testing.assert_allclose(other.residuals, est.residuals, rtol=1e-6)
    assert [alignment._wrap(a) for a in (-180.0, 540.0, -190.0, 190.0, 0.0)] == [180.0, 180.0, 170.0, -170.0, 0.0]


def test_a_full_turn_search_covers_the_seam(turned_render):
    """The truth near the seam: the probe given turned by -145 degrees, so the image is explained by a yaw of
    170 (= -190). A full-turn search (coarse grid of every 45 degrees from -180, all of them evaluated) finds
    it across the seam and reports it in (-180, 180]."""
    probe, brdf, render = turned_render
    est = alignment.estimate_yaw(render.image, probe.rotated(euler_deg=(0, -145, 0)), render.geometry, brdf=brdf,
                                 n_normals=400, grid=(8, 8), coarse_step_deg=45.0, tol_deg=1.0)
    assert abs(est.yaw_deg - 170.0) < 2.0, est.summary()
    assert set(np.arange(-180.0, 180.0, 45.0)) <= set(est.angles_deg)


def test_the_given_alpha_weighs_the_per_candidate_solve(turned_render):
    """Material unknown: the regularisation weight passed is the one each candidate's solve uses. A
    regularised fit explains the data no better as its weight grows, so the best residual with alpha = 100
    is clearly above the one with alpha = 1e-4 (measured 0.16 against 0.08)."""
    probe, _, render = turned_render
    small = dict(n_normals=400, grid=(8, 8), texel_width=32, search_deg=(24.0, 26.0), coarse_step_deg=2.0, tol_deg=2.0)
    loose, tight = (alignment.estimate_yaw(render.image, probe, render.geometry, alpha=a, **small) for a in (1e-4, 1e2))
    assert tight.residual > 1.5 * loose.residual, (loose.summary(), tight.summary())
