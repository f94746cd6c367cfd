"""Closed-form BRDFs: normalisation, reciprocity, Mitsuba agreement, spec parsing, MERL tabulation."""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_bivariate.analytic import (
    BivariateLobe,
    CookTorranceGGX,
    Lambertian,
    OrenNayar,
    analytic_from_spec,
    to_merl,
)
from mi_bivariate.errors import InputError
from mi_bivariate.merl import node_angles

MODELS = [
    Lambertian([0.8, 0.5, 0.2]),
    CookTorranceGGX([0.1, 0.2, 0.3], [1.0, 0.9, 0.8], alpha=0.2, ior=1.5),
    OrenNayar([0.7, 0.6, 0.5], sigma=0.4),
    BivariateLobe([0.1, 0.2, 0.3], [4.0, 5.0, 6.0], width=0.15, f0=0.2),
]


def hemisphere_grid(n_theta: int = 400, n_phi: int = 800):
    """Midpoint quadrature on the upper hemisphere: directions (n_theta * n_phi, 3) and weights dw (sr)."""
    theta = (np.arange(n_theta) + 0.5) * (0.5 * math.pi / n_theta)
    phi = (np.arange(n_phi) + 0.5) * (2.0 * math.pi / n_phi)
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    dirs = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3)
    dw = (np.sin(th) * (0.5 * math.pi / n_theta) * (2.0 * math.pi / n_phi)).reshape(-1)
    return dirs, dw


def directional_albedo(brdf, wo: np.ndarray, grid=None) -> np.ndarray:
    """int f(wi, wo) cos(theta_i) dwi, ``(3,)``."""
    wi, dw = grid if grid is not None else hemisphere_grid()
    f = brdf.eval_dirs(wi, np.broadcast_to(wo, wi.shape))
    return np.sum(f * (wi[:, 2] * dw)[:, None], axis=0)


def random_pairs(rng, n):
    v = rng.normal(size=(2, n, 3))
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    v[..., 2] = np.abs(v[..., 2])
    return v[0], v[1]


def test_lambertian_albedo_integral():
    grid = hemisphere_grid()
    for theta_o in (0.0, 0.7, 1.3):
        wo = np.array([math.sin(theta_o), 0.0, math.cos(theta_o)])
        np.testing.assert_allclose(directional_albedo(Lambertian([0.8, 0.5, 0.2]), wo, grid), [0.8, 0.5, 0.2],
                                   rtol=1e-5)


def test_ggx_distribution_normalised():
    h, dw = hemisphere_grid(2000, 8)  # isotropic: few azimuths suffice
    for alpha in (0.05, 0.2, 0.6):
        model = CookTorranceGGX(alpha=alpha)
        assert abs(np.sum(model.distribution(h[:, 2]) * h[:, 2] * dw) - 1.0) < 2e-3


def test_ggx_white_furnace_bounded():
    grid = hemisphere_grid()
    model = CookTorranceGGX(0.0, 1.0, alpha=0.3, ior=None)
    albedos = []
    for theta_o in np.linspace(0.0, 1.4, 8):
        wo = np.array([math.sin(theta_o), 0.0, math.cos(theta_o)])
        albedos.append(directional_albedo(model, wo, grid)[0])
    albedos = np.array(albedos)
    # Separable Smith masking loses energy (no multiple scattering) but never creates it.
    assert np.all(albedos <= 1.0 + 2e-3), albedos
    assert np.all(albedos > 0.75), albedos
    # At normal view the reflection of h at angle theta_h leaves at 2 theta_h:
    # a 1D integral over theta_h < pi/4 (beyond, wi is below the horizon).
    alpha = 0.3
    theta_h = (np.arange(20000) + 0.5) * (0.25 * math.pi / 20000)
    d = alpha**2 / (math.pi * (np.cos(theta_h) ** 2 * (alpha**2 - 1.0) + 1.0) ** 2)
    g1 = 2.0 / (1.0 + np.sqrt(1.0 + alpha**2 * np.tan(2.0 * theta_h) ** 2))
    expected = np.sum(d * np.cos(theta_h) * g1 * 2.0 * math.pi * np.sin(theta_h)) * (0.25 * math.pi / 20000)
    assert abs(albedos[0] - expected) < 2e-3, (albedos[0], expected)


def test_ggx_matches_mitsuba_roughconductor():
    rng = np.random.default_rng(0)
    wi, wo = random_pairs(rng, 4000)
    model = CookTorranceGGX(0.0, 1.0, alpha=0.25, ior=1.5)
    bsdf = mi.load_dict({"type": "roughconductor", "distribution": "ggx", "alpha": 0.25,
                         "eta": 1.5, "k": 0.0, "sample_visible": False})
    si = dr.zeros(mi.SurfaceInteraction3f, wo.shape[0])
    si.wi = mi.Vector3f(wo.T.astype(np.float32))
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    value = bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(wi.T.astype(np.float32)))
    reference = np.array(value).T / wi[:, 2:3]  # Mitsuba returns f * cos(theta_i)
    got = model.eval_dirs(wi.astype(np.float32).astype(np.float64), wo.astype(np.float32).astype(np.float64))
    keep = (wi[:, 2] > 0.05) & (wo[:, 2] > 0.05)
    np.testing.assert_allclose(got[keep], reference[keep], rtol=2e-3, atol=1e-5)


def test_oren_nayar():
    rng = np.random.default_rng(1)
    wi, wo = random_pairs(rng, 3000)
    np.testing.assert_allclose(OrenNayar([0.7, 0.6, 0.5], 0.0).eval_dirs(wi, wo),
                               Lambertian([0.7, 0.6, 0.5]).eval_dirs(wi, wo), rtol=1e-14)

    # A second implementation in explicit spherical angles.
    sigma, rho = 0.4, 0.7
    model = OrenNayar(rho, sigma)
    theta_i, theta_o = np.arccos(wi[:, 2]), np.arccos(wo[:, 2])
    phi_i, phi_o = np.arctan2(wi[:, 1], wi[:, 0]), np.arctan2(wo[:, 1], wo[:, 0])
    a = 1.0 - 0.5 * sigma**2 / (sigma**2 + 0.33)
    b = 0.45 * sigma**2 / (sigma**2 + 0.09)
    alpha, beta = np.maximum(theta_i, theta_o), np.minimum(theta_i, theta_o)
    expected = rho / math.pi * (a + b * np.maximum(0.0, np.cos(phi_i - phi_o)) * np.sin(alpha) * np.tan(beta))
    np.testing.assert_allclose(model.eval_dirs(wi, wo)[:, 0], expected, rtol=1e-9)

    # Retro-reflection: back towards the light is brighter than the mirror direction.
    theta = 1.0
    w = np.array([math.sin(theta), 0.0, math.cos(theta)])
    mirror = np.array([-math.sin(theta), 0.0, math.cos(theta)])
    assert model.eval_dirs(w, w)[0] > 1.3 * model.eval_dirs(w, mirror)[0]


def test_oren_nayar_near_the_normal():
    """The published form (written out) where one direction is within a few degrees of the normal, which the
    model's guard against the undefined azimuth at the normal itself must not reach; at the normal, Lambertian
    times A (sin(beta) = 0)."""
    sigma, rho = 0.5, 0.6
    model = OrenNayar(rho, sigma)
    a = 1.0 - 0.5 * sigma**2 / (sigma**2 + 0.33)
    b = 0.45 * sigma**2 / (sigma**2 + 0.09)
    for theta_i, theta_o, dphi in [(0.02, 1.2, 0.0), (0.05, 0.08, 0.3), (0.01, 0.5, 1.0), (0.7, 0.003, 0.0)]:
        wi = np.array([math.sin(theta_i), 0.0, math.cos(theta_i)])
        wo = np.array([math.sin(theta_o) * math.cos(dphi), math.sin(theta_o) * math.sin(dphi), math.cos(theta_o)])
        alpha, beta = max(theta_i, theta_o), min(theta_i, theta_o)
        want = rho / math.pi * (a + b * max(0.0, math.cos(dphi)) * math.sin(alpha) * math.tan(beta))
        assert model.eval_dirs(wi, wo)[0] == pytest.approx(want, rel=1e-12)
    normal = np.array([0.0, 0.0, 1.0])
    assert model.eval_dirs(normal, np.array([0.6, 0.0, 0.8]))[0] == pytest.approx(rho / math.pi * a, rel=1e-12)


@pytest.mark.parametrize("model", MODELS, ids=lambda m: m.kind)
def test_reciprocity_and_horizon(model):
    rng = np.random.default_rng(2)
    wi, wo = random_pairs(rng, 2000)
    f = model.eval_dirs(wi, wo)
    assert np.all(np.isfinite(f)) and f.min() >= 0.0
    np.testing.assert_allclose(model.eval_dirs(wo, wi), f, rtol=1e-10)
    below = wo * np.array([1.0, 1.0, -1.0])
    assert np.all(model.eval_dirs(wi, below) == 0.0)


def test_angle_and_direction_forms_agree():
    from mi_bivariate.coordinates import half_diff_from_dirs

    rng = np.random.default_rng(3)
    wi, wo = random_pairs(rng, 2000)
    theta_h, _, theta_d, phi_d = half_diff_from_dirs(wi, wo)
    for model in MODELS:
        np.testing.assert_allclose(model.eval(theta_h, theta_d, phi_d), model.eval_dirs(wi, wo),
                                   rtol=1e-9, atol=1e-12)


def test_bivariate_lobe_ignores_phi_d():
    lobe = MODELS[3]
    theta_h, theta_d = np.meshgrid(np.linspace(0, 0.6, 20), np.linspace(0, 0.9, 20), indexing="ij")
    ref = lobe.eval_half_diff(theta_h, theta_d)
    for phi_d in (0.0, 0.4, 1.5, 2.9):  # all valid: theta_h + theta_d < pi/2
        np.testing.assert_allclose(lobe.eval(theta_h, theta_d, phi_d), ref, rtol=1e-12)
    # Its specular peak and its Fresnel-like growth towards grazing theta_d.
    np.testing.assert_allclose(ref[0, 0], lobe.diffuse / math.pi + lobe.specular * lobe.f0)
    assert np.all(np.diff(ref[0, :, 0]) >= 0.0)


@pytest.mark.parametrize("model", MODELS, ids=lambda m: m.kind)
def test_tabulated_nodes_equal_closed_form(model):
    merl = to_merl(model)
    theta_h, theta_d, phi_d = node_angles()
    ii, jj, kk = np.meshgrid(np.arange(0, 90, 7), np.arange(0, 90, 11), np.arange(0, 180, 13), indexing="ij")
    th, td, pd = theta_h[ii], theta_d[jj], phi_d[kk]
    looked_up = merl.eval(th, td, pd)
    valid = merl.valid_mask()[ii, jj, kk]
    assert valid.mean() > 0.5
    np.testing.assert_allclose(looked_up[valid], model.eval(th, td, pd)[valid], rtol=1e-12)
    assert np.all(np.isnan(looked_up[~valid]))


def test_spec_parser():
    ggx = analytic_from_spec("ggx:alpha=0.1,specular=0.5,diffuse=0.2,0.1,0.05")
    assert isinstance(ggx, CookTorranceGGX) and ggx.alpha == 0.1 and ggx.ior == 1.5
    np.testing.assert_array_equal(ggx.albedo_diffuse, [0.2, 0.1, 0.05])
    np.testing.assert_array_equal(ggx.specular, [0.5, 0.5, 0.5])
    lamb = analytic_from_spec("lambertian:albedo=0.5,0.5,0.5")
    np.testing.assert_array_equal(lamb.albedo, [0.5, 0.5, 0.5])
    assert isinstance(analytic_from_spec("oren-nayar:albedo=0.3,sigma=0.2"), OrenNayar)
    assert isinstance(analytic_from_spec("bivariate-lobe"), BivariateLobe)
    for model in MODELS:  # names are specs that parse back to the same model
        again = analytic_from_spec(model.name)
        assert type(again) is type(model) and again.name == model.name


@pytest.mark.parametrize("spec", ["phong:n=10", "ggx:beta=0.1", "ggx:alpha=fast", "lambertian:albedo=0.1,0.2",
                                  "ggx:alpha=-1", "ggx:0.1", "ggx:alpha=0.1,alpha=0.2", "ggx:ior=0.5",
                                  # absurd sizes overflowed float32 downstream and were blamed on "mean"
                                  "ggx:diffuse=1e38", "lambertian:albedo=nan", "ggx:alpha=inf",
                                  # negative reflectances, an index of 1 and a zero-width or f0 > 1 lobe
                                  "lambertian:albedo=-0.5", "ggx:specular=0.1,-0.2,0.3", "ggx:ior=1",
                                  "bivariate-lobe:width=0", "bivariate-lobe:f0=1.5",
                                  # a second value of a one-value key was dropped silently; a negative roughness
                                  "ggx:alpha=0.1,0.2", "oren-nayar:sigma=0.3,0.4", "oren-nayar:sigma=-0.3"])
def test_spec_parser_errors(spec):
    with pytest.raises(InputError) as info:
        analytic_from_spec(spec)
    assert spec in str(info.value)


def test_bivariate_lobe_closed_form_at_chosen_angles():
    """The lobe's documented formula, written out here, at pairs built from (theta_h, theta_d) by hand:
    h tilted by theta_h about y, wi and wo at theta_d either side of h in the plane of h and y."""
    lobe = BivariateLobe([0.1, 0.2, 0.3], [4.0, 5.0, 6.0], width=0.15, f0=0.2)
    theta_h = np.array([0.0, 0.1, 0.2, 0.05])
    theta_d = np.array([0.3, 0.9, 0.5, 1.2])
    h = np.stack([np.sin(theta_h), 0.0 * theta_h, np.cos(theta_h)], -1)
    y = np.array([0.0, 1.0, 0.0])
    wi = np.cos(theta_d)[:, None] * h + np.sin(theta_d)[:, None] * y
    wo = np.cos(theta_d)[:, None] * h - np.sin(theta_d)[:, None] * y
    shape = np.exp(-(theta_h / 0.15) ** 2) * (0.2 + 0.8 * (1.0 - np.cos(theta_d)) ** 5)
    want = np.array([0.1, 0.2, 0.3]) / math.pi + shape[:, None] * np.array([4.0, 5.0, 6.0])
    np.testing.assert_allclose(lobe.eval_dirs(wi, wo), want, rtol=1e-9)


def test_spec_limits_are_inclusive_and_tables_keep_their_precision():
    """A parameter of exactly MAX_PARAMETER is accepted ("at most"); ``to_merl(dtype=np.float32)`` (the evaluation's
    analytic truths, as precise as the renders) stores the closed form rounded to float32 once."""
    from mi_bivariate.analytic import MAX_PARAMETER

    assert analytic_from_spec(f"lambertian:albedo={MAX_PARAMETER:g}").albedo[0] == MAX_PARAMETER
    model = Lambertian([0.7, 0.6, 0.5])
    merl32 = to_merl(model, dtype=np.float32)  # (float64 by default: test_tabulated_nodes_equal_closed_form)
    assert merl32.table.dtype == np.float32
    np.testing.assert_array_equal(merl32.table[40, 30, 77], (np.array([0.7, 0.6, 0.5]) / math.pi).astype(np.float32))
