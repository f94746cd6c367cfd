"""The ``bivariate`` and ``merl`` BSDF plugins: lookups, sampling, renders, gradients."""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from helpers import suite_variant, sun_sky_probe
from mitsuba.chi2 import BSDFAdapter, ChiSquareTest, SphericalDomain

from mi_bivariate.analytic import BivariateLobe, CookTorranceGGX, Lambertian, to_merl
from mi_bivariate.bivariate import BivariateBRDF
from mi_bivariate.common import luminance
from mi_bivariate.coordinates import half_diff_from_dirs, st_from_dirs
from mi_bivariate.errors import InputError, InputWarning
from mi_bivariate.geometry import SphereCamera
from mi_bivariate.merl import MERLBRDF, geometric_mask
from mi_bivariate.plugins._tabulated import half_vector_profile
from mi_bivariate.probes import Probe
from mi_bivariate.render import bsdf_dict, sphere_scene_dict
from mi_bivariate.variants import ensure_variant

RHO = np.array([0.2, 0.5, 0.8])


def lobe_table(width: float, diffuse: float, specular: float, n: int = 32) -> BivariateBRDF:
    """A bivariate lobe (analytic closed form) sampled on an n x n st grid."""
    lobe = BivariateLobe(diffuse=diffuse, specular=specular, width=width)
    theta_h = 0.5 * math.pi * np.linspace(0.0, 1.0, n) ** 2
    theta_d = 0.5 * math.pi * np.linspace(0.0, 1.0, n)
    return BivariateBRDF(lobe.eval_half_diff(theta_h[:, None], theta_d[None, :]))


def lambertian_table(n: int = 8) -> BivariateBRDF:
    return BivariateBRDF(np.broadcast_to(RHO / math.pi, (n, n, 3)))


def merl_dict(merl: MERLBRDF, interpolation: str = "linear", **extra) -> dict:
    return {**bsdf_dict(merl, interpolation=interpolation), **extra}


def random_pairs(n: int, seed: int, min_cos: float = 0.0):
    """``n`` random direction pairs on the upper hemisphere, ``(n, 3) float64`` each."""
    rng = np.random.default_rng(seed)

    def hemisphere():
        v = rng.normal(size=(4 * n, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        v[:, 2] = np.abs(v[:, 2])
        return v[v[:, 2] > min_cos][:n]

    return hemisphere(), hemisphere()


def plugin_eval(bsdf, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """``bsdf.eval`` (includes cos theta_o) at local direction pairs -> ``(n, 3)``."""
    si = dr.zeros(mi.SurfaceInteraction3f, len(wi))
    si.wi = mi.Vector3f(*(mi.Float(wi[:, k].astype(np.float32)) for k in range(3)))
    wo_dr = mi.Vector3f(*(mi.Float(wo[:, k].astype(np.float32)) for k in range(3)))
    return np.array(bsdf.eval(mi.BSDFContext(), si, wo_dr), np.float64).T  # (3, n) -> (n, 3)


# ------------------------------------------------------------------ set-up

def test_register_is_idempotent_per_variant():
    from mi_bivariate.plugins import plugin_classes, register

    classes = plugin_classes()
    register()
    register()
    assert plugin_classes() is classes
    assert ensure_variant() == suite_variant()
    bsdf = mi.load_dict(bsdf_dict(lambertian_table()))
    assert "BivariateBSDF" in str(bsdf)
    flags = bsdf.flags()
    assert mi.has_flag(flags, mi.BSDFFlags.GlossyReflection) and mi.has_flag(flags, mi.BSDFFlags.FrontSide)
    assert not mi.has_flag(flags, mi.BSDFFlags.BackSide)


def test_plugin_classes_before_register_still_registers_in_a_fresh_process():
    """``plugin_classes()`` builds the classes; the registry is a separate matter: a later ``register()``
    (or ``ensure_variant()``) must still put them in this variant's registry."""
    import subprocess
    import sys

    code = (f"import mitsuba as mi, numpy as np; mi.set_variant({suite_variant()!r})\n"
            "from mi_bivariate.plugins import plugin_classes, register\n"
            "plugin_classes(); register()\n"
            "print(mi.load_dict({'type': 'bivariate', 'table': mi.Bitmap(np.full((4, 4, 3), 0.1, np.float32))}))\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and "BivariateBSDF" in run.stdout, run.stderr[-2000:]


@pytest.mark.parametrize("props, message", [
    ({"type": "bivariate"}, "needs a 'filename'"),
    ({"type": "bivariate", "table": "nope"}, "must be a mitsuba.Bitmap"),
    ({"type": "bivariate", "filename": "/no/such/file.npz"}, "not found"),
    ({"type": "merl", "filename": "/no/such/file.binary"}, "MERL file not found"),
    ({"type": "bivariate", "sampling": "magic"}, "sampling must be"),
])
def test_bad_properties_raise_readable_errors(props, message):
    with pytest.raises(RuntimeError, match=message):
        mi.load_dict(props)


def test_bad_tables_raise_readable_errors():
    bad = np.full((4, 4, 3), 0.1, np.float32)
    bad[1, 2, 0] = np.nan
    with pytest.raises(RuntimeError, match="NaN"):
        mi.load_dict({"type": "bivariate", "table": mi.Bitmap(bad)})
    with pytest.raises(RuntimeError, match="8100 x 180"):
        mi.load_dict({"type": "merl", "table": mi.Bitmap(np.ones((90, 180, 3), np.float32))})
    with pytest.raises(RuntimeError, match="interpolation"):
        mi.load_dict({**bsdf_dict(Lambertian(0.5)), "interpolation": "cubic"})


# ------------------------------------------------------------ evaluation

def test_bivariate_eval_matches_closed_form():
    # A table bilinear in (s, t) is reproduced exactly by bilinear interpolation.
    n_t, n_s = 9, 5
    t, s = np.meshgrid(np.linspace(0, 1, n_t), np.linspace(0, 1, n_s), indexing="ij")
    coeff = np.array([[0.3, 0.1, 0.05], [0.2, 0.4, 0.1], [0.05, 0.0, 0.3]])  # f = c0 + c1 t + c2 s t
    table = coeff[0] + coeff[1] * t[..., None] + coeff[2] * (s * t)[..., None]
    bsdf = mi.load_dict({"type": "bivariate", "table": mi.Bitmap(table.astype(np.float32))})
    wi, wo = random_pairs(2000, seed=1)
    s_ref, t_ref = st_from_dirs(wo, wi)
    expected = coeff[0] + coeff[1] * t_ref[:, None] + coeff[2] * (s_ref * t_ref)[:, None]
    got = plugin_eval(bsdf, wi, wo) / wo[:, 2:3]
    np.testing.assert_allclose(got, expected, rtol=2e-4, atol=1e-5)

    # Known angles: mirror configuration at normal incidence -> node (0, 0).
    n = np.array([[0.0, 0.0, 1.0]])
    np.testing.assert_allclose(plugin_eval(bsdf, n, n)[0], table[0, 0], rtol=1e-6)
    # One-sided: zero when either direction is below the horizon.
    below = np.array([[0.3, 0.0, -0.95]])
    assert np.all(plugin_eval(bsdf, n, below / np.linalg.norm(below)) == 0.0)
    assert np.all(plugin_eval(bsdf, below / np.linalg.norm(below), n) == 0.0)


def test_bivariate_eval_matches_numpy_table_lookup():
    biv = lobe_table(width=0.15, diffuse=0.3, specular=4.0)
    bsdf = mi.load_dict(bsdf_dict(biv))
    wi, wo = random_pairs(4000, seed=2)
    theta_h, _, theta_d, _ = half_diff_from_dirs(wo, wi)
    expected = biv.eval(theta_h, theta_d)
    got = plugin_eval(bsdf, wi, wo) / wo[:, 2:3]
    np.testing.assert_allclose(got, expected, rtol=1e-3, atol=1e-4)


@pytest.fixture(scope="module")
def ggx_merl() -> MERLBRDF:
    return to_merl(CookTorranceGGX(albedo_diffuse=0.2, specular=1.0, alpha=0.2, ior=1.5), dtype=np.float32)


@pytest.mark.parametrize("interpolation", ["nearest", "linear"])
def test_merl_eval_matches_merl_module(ggx_merl, interpolation):
    # Away from the horizon every lookup's nodes are measured, so the plugin
    # (float32, Dr.Jit) must agree with MERLBRDF.eval (float64, numpy).
    bsdf = mi.load_dict(merl_dict(ggx_merl, interpolation))
    wi, wo = random_pairs(4000, seed=3, min_cos=0.35)
    theta_h, _, theta_d, phi_d = half_diff_from_dirs(wo, wi)
    expected = ggx_merl.eval(theta_h, theta_d, phi_d, interpolation=interpolation)
    ok = np.all(np.isfinite(expected), axis=1)
    got = plugin_eval(bsdf, wi, wo) / wo[:, 2:3]
    close = np.all(np.isclose(got, expected, rtol=2e-3, atol=1e-5), axis=1)
    # Nearest lookups may floor to the neighbouring node when an angle is within
    # float32 rounding of a node boundary: allow a handful of those.
    allowed = 0.002 if interpolation == "nearest" else 0.0
    assert ok.mean() > 0.99
    assert np.mean(~close[ok]) <= allowed


@pytest.mark.parametrize("interpolation", ["nearest", "linear"])
def test_merl_eval_matches_merl_module_on_a_table_without_symmetry(interpolation):
    """Independent random values at every measured node: unlike a smooth analytic lobe (the test above),
    f(phi_d) differs from f(-phi_d) and from its neighbours, so a lookup that mirrors phi_d instead of
    folding it by pi, drops the wrap from node 179 to node 0, or blurs along phi_d is seen."""
    rng = np.random.default_rng(13)
    table = np.where(geometric_mask()[..., None], rng.uniform(0.1, 1.0, (90, 90, 180, 3)), np.nan).astype(np.float32)
    merl = MERLBRDF(table)
    bsdf = mi.load_dict(merl_dict(merl, interpolation))
    wi, wo = random_pairs(4000, seed=14, min_cos=0.35)
    theta_h, _, theta_d, phi_d = half_diff_from_dirs(wo, wi)
    expected = merl.eval(theta_h, theta_d, phi_d, interpolation=interpolation)
    ok = np.all(np.isfinite(expected), axis=1)
    close = np.all(np.isclose(plugin_eval(bsdf, wi, wo) / wo[:, 2:3], expected, rtol=2e-3, atol=1e-5), axis=1)
    assert ok.mean() > 0.99
    # Nearest lookups may floor to the neighbouring node within float32 rounding of a node boundary.
    assert np.mean(~close[ok]) <= (0.002 if interpolation == "nearest" else 0.0)


@pytest.mark.parametrize("plugin", ["bivariate", "merl"])
def test_a_context_without_reflection_gets_nothing(plugin):
    """A ``BSDFContext`` whose type mask leaves out diffuse and glossy reflection (an integrator asking for
    delta lobes only) gets zero value, pdf and sample weight, as from Mitsuba's own ``diffuse``."""
    table = lambertian_table()
    props = bsdf_dict(table) if plugin == "bivariate" else merl_dict(table.to_merl(), "nearest")
    ctx = mi.BSDFContext()
    ctx.type_mask = +mi.BSDFFlags.DeltaReflection
    wi, wo = random_pairs(100, seed=12, min_cos=0.2)
    si = dr.zeros(mi.SurfaceInteraction3f, len(wi))
    si.wi = mi.Vector3f(*(mi.Float(wi[:, k].astype(np.float32)) for k in range(3)))
    wo_dr = mi.Vector3f(*(mi.Float(wo[:, k].astype(np.float32)) for k in range(3)))
    rng = np.random.default_rng(12)
    for bsdf in (mi.load_dict({"type": "diffuse"}), mi.load_dict(props)):
        value, pdf = bsdf.eval_pdf(ctx, si, wo_dr)
        bs, weight = bsdf.sample(ctx, si, mi.Float(rng.random(len(wi))), mi.Point2f(rng.random((2, len(wi)))))
        for result in (bsdf.eval(ctx, si, wo_dr), bsdf.pdf(ctx, si, wo_dr), value, pdf, weight, bs.pdf):
            assert np.all(np.array(result) == 0.0), str(bsdf)


# ---------------------------------------------------------- sampling (chi2)

@pytest.fixture(scope="module")
def chi2_tables() -> dict:
    diffuse_ish = lobe_table(width=0.5, diffuse=0.6, specular=0.3)
    glossy = lobe_table(width=0.05, diffuse=0.05, specular=20.0)
    # alpha 0.05 samples correctly too (a fine pdf integral agrees), but the chi2
    # reference quadrature at the pole then needs ires=24 (twice the time).
    glossy_merl = to_merl(CookTorranceGGX(albedo_diffuse=0.05, specular=1.0, alpha=0.08, ior=1.5), dtype=np.float32)
    return {
        ("bivariate", "diffuse"): bsdf_dict(diffuse_ish),
        ("bivariate", "glossy"): bsdf_dict(glossy),
        ("merl", "diffuse"): merl_dict(diffuse_ish.to_merl(), "linear"),
        ("merl", "glossy"): merl_dict(glossy_merl, "nearest"),
    }


@pytest.mark.parametrize("plugin", ["bivariate", "merl"])
@pytest.mark.parametrize("material", ["diffuse", "glossy"])
@pytest.mark.parametrize("theta_deg", [0.0, 45.0, 75.0])
def test_sample_agrees_with_pdf(chi2_tables, plugin, material, theta_deg):
    props = chi2_tables[(plugin, material)]
    theta = math.radians(theta_deg)
    wi = [math.sin(theta), 0.0, math.cos(theta)]
    sample_func, pdf_func = BSDFAdapter(plugin, props, wi=wi)
    # ires=12: the chi2 reference integrates the pdf per cell with the trapezoid
    # rule, which needs fine steps for the sharp lobe near the pole.
    chi2 = ChiSquareTest(domain=SphericalDomain(), sample_func=sample_func, pdf_func=pdf_func,
                         sample_dim=3, sample_count=1_000_000, res=101, ires=12, seed=7)
    assert chi2.run(significance_level=0.01, test_count=12, quiet=True), chi2.messages


@pytest.mark.parametrize("plugin", ["bivariate", "merl"])
@pytest.mark.parametrize("theta_deg", [0.0, 45.0, 80.0])
def test_sample_weight_is_eval_over_pdf(chi2_tables, plugin, theta_deg):
    """``sample``'s weight is ``eval / pdf`` at the sampled direction (chi2's adapter turns weights into
    0 or 1, so the chi2 test above cannot see a wrong weight), its ``pdf`` is ``pdf()``'s, and a direction
    at or below the horizon has weight 0."""
    bsdf = mi.load_dict(chi2_tables[(plugin, "glossy")])
    n = 20000
    theta = math.radians(theta_deg)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(math.sin(theta), 0.0, math.cos(theta))
    rng = np.random.default_rng(5)
    ctx = mi.BSDFContext()
    bs, weight = bsdf.sample(ctx, si, mi.Float(rng.random(n, np.float32)),
                             mi.Point2f(*(mi.Float(rng.random(n, np.float32)) for _ in range(2))))
    value, pdf = np.array(bsdf.eval(ctx, si, bs.wo), np.float64).T, np.array(bsdf.pdf(ctx, si, bs.wo), np.float64)
    weight, sampled_pdf = np.array(weight, np.float64).T, np.array(bs.pdf, np.float64)
    up = np.array(bs.wo.z) > 0.0
    assert up.mean() > 0.5 and np.all(weight[~up] == 0.0) and np.all(sampled_pdf[~up] == 0.0)
    np.testing.assert_allclose(sampled_pdf[up], pdf[up], rtol=1e-6)
    np.testing.assert_allclose(weight[up], value[up] / pdf[up][:, None], rtol=1e-5, atol=1e-7)


def test_pdf_integrates_to_reflected_mass():
    # Independent of chi2: integrate the pdf on a fine (cos theta, phi) grid.
    bsdf = mi.load_dict(bsdf_dict(lobe_table(width=0.05, diffuse=0.05, specular=20.0)))
    n = 1000
    c = (np.arange(n) + 0.5) / n
    p = (np.arange(2 * n) + 0.5) / (2 * n) * 2 * math.pi
    cc, pp = np.meshgrid(c, p, indexing="ij")
    ss = np.sqrt(1 - cc * cc)
    wo = np.stack([ss * np.cos(pp), ss * np.sin(pp), cc], -1).reshape(-1, 3)
    si = dr.zeros(mi.SurfaceInteraction3f, len(wo))
    si.wi = mi.Vector3f(0.0, 0.0, 1.0)
    pdf = np.array(bsdf.pdf(mi.BSDFContext(), si, mi.Vector3f(*(mi.Float(wo[:, k]) for k in range(3)))))
    assert abs(pdf.sum() * (1.0 / n) * (math.pi / n) - 1.0) < 5e-3


def test_pdf_matches_a_numpy_evaluation_at_a_sharp_peak():
    """The mixture pdf ``p_c cos(theta_o) / pi + (1 - p_c) p_x(x) / (2 pi) / (4 |wo . h|)`` evaluated in float64
    numpy from the sampling profile, at outgoing directions whose half vector lies within 2e-3 rad of the
    normal: the chi2 tests' cells are far too coarse to see the pdf there. Computed as ``1 - h.z`` in float32,
    ``x = 1 - cos(theta_h)`` is quantised in steps of 6e-8 (theta_h 3.5e-4 rad), which put the pdf of this
    lobe up to 100% off its sampling density (measured): renders of near-mirror materials would be biased."""
    n = 32
    biv = lobe_table(width=0.003, diffuse=0.02, specular=200.0, n=n)
    bsdf = mi.load_dict(bsdf_dict(biv))
    profile = half_vector_profile(luminance(np.asarray(biv.table, np.float64)), np.linspace(0, 1, n),
                                  np.linspace(0, 1, n))
    rng = np.random.default_rng(9)
    theta_h, phi_h = rng.uniform(0.0, 2e-3, 2000), rng.uniform(0.0, 2.0 * math.pi, 2000)
    h = np.stack([np.sin(theta_h) * np.cos(phi_h), np.sin(theta_h) * np.sin(phi_h), np.cos(theta_h)], -1)
    wi = np.array([math.sin(0.7), 0.0, math.cos(0.7)])
    wo = 2.0 * (h @ wi)[:, None] * h - wi
    x = 2.0 * np.sin(0.5 * theta_h) ** 2
    p_x = np.interp(x, profile.x_nodes, profile.density) / np.trapezoid(profile.density, profile.x_nodes)
    p_c = profile.cosine_weight
    expected = p_c * wo[:, 2] / math.pi + (1.0 - p_c) * p_x / (2.0 * math.pi) / (4.0 * np.sum(wo * h, axis=-1))
    si = dr.zeros(mi.SurfaceInteraction3f, len(wo))
    si.wi = mi.Vector3f(*(float(v) for v in wi))
    got = np.array(bsdf.pdf(mi.BSDFContext(), si, mi.Vector3f(*(mi.Float(wo[:, k].astype(np.float32))
                                                               for k in range(3)))), np.float64)
    assert expected.max() > 1000.0  # a sharp lobe
    np.testing.assert_allclose(got, expected, rtol=1e-3)


# ---------------------------------------------------------------- renders

def render(bsdf: dict, probe: Probe, seed: int = 0, spp: int = 64, res: int = 32) -> np.ndarray:
    cam = SphereCamera.create("orthographic", res)
    scene = mi.load_dict(sphere_scene_dict(bsdf, probe, cam, normals=False))
    return np.array(mi.render(scene, spp=spp, seed=seed), np.float64)[..., :3]


def disc(res: int = 32) -> np.ndarray:

    return SphereCamera.create("orthographic", res).coverage_mask()


def assert_same_to_noise(a, b, mask, seeds_a, seeds_b, slack=1.3):
    """Two renderers agree when their difference is no larger than their noise.

    ``a``/``b`` are callables seed -> image; the noise of each is estimated
    from two seeds of itself.
    """
    a0, a1 = a(seeds_a[0])[mask], a(seeds_a[1])[mask]
    b0, b1 = b(seeds_b[0])[mask], b(seeds_b[1])[mask]
    noise2 = 0.5 * (np.mean((a0 - a1) ** 2) + np.mean((b0 - b1) ** 2))
    cross2 = 0.5 * (np.mean((a0 - b1) ** 2) + np.mean((a1 - b0) ** 2))
    assert cross2 < slack * noise2, (cross2, noise2)
    ratio = (a0.sum(0) + a1.sum(0)) / (b0.sum(0) + b1.sum(0))
    np.testing.assert_allclose(ratio, 1.0, atol=0.01)


@pytest.mark.parametrize("plugin", ["bivariate", "merl"])
def test_furnace(plugin):
    table = lambertian_table()
    bsdf = bsdf_dict(table) if plugin == "bivariate" else merl_dict(table.to_merl(), "nearest")
    img = render(bsdf, Probe.constant(1.0, 16))
    m = disc()
    np.testing.assert_allclose(img[m].mean(0), RHO, rtol=3e-3)
    assert np.abs(img[m] / RHO - 1).max() < 0.2


def test_bivariate_matches_builtin_diffuse():
    probe = sun_sky_probe()
    ours = bsdf_dict(lambertian_table())
    builtin = {"type": "diffuse", "reflectance": {"type": "rgb", "value": RHO.tolist()}}
    assert_same_to_noise(lambda s: render(ours, probe, s), lambda s: render(builtin, probe, s), disc(),
                         (0, 1), (2, 3))


def test_merl_plugin_agrees_with_bivariate_plugin():
    biv = lobe_table(width=0.2, diffuse=0.3, specular=2.0)
    probe = sun_sky_probe()
    a = bsdf_dict(biv)
    b = merl_dict(biv.to_merl(), "linear")
    assert_same_to_noise(lambda s: render(a, probe, s), lambda s: render(b, probe, s), disc(), (0, 1), (2, 3))


def test_filename_properties(tmp_path):
    biv = lobe_table(width=0.2, diffuse=0.3, specular=2.0, n=8)
    biv.save(tmp_path / "t.npz")
    biv.write_merl(tmp_path / "t.binary")
    wi, wo = random_pairs(500, seed=4, min_cos=0.3)
    from_file = mi.load_dict({"type": "bivariate", "filename": str(tmp_path / "t.npz")})
    from_bitmap = mi.load_dict(bsdf_dict(biv))
    np.testing.assert_array_equal(plugin_eval(from_file, wi, wo), plugin_eval(from_bitmap, wi, wo))
    merl = mi.load_dict({"type": "merl", "filename": str(tmp_path / "t.binary"), "interpolation": "linear"})
    np.testing.assert_allclose(plugin_eval(merl, wi, wo), plugin_eval(from_bitmap, wi, wo), rtol=0.02, atol=1e-4)
    # Down to the horizon, where the MERL lookups read the nodes below it that the plugin fills (from the
    # phi_d mean: a bivariate table comes back; 0 there would be 100% off): 3.3% at most measured.
    wi, wo = random_pairs(5000, seed=5, min_cos=0.0)
    np.testing.assert_allclose(plugin_eval(merl, wi, wo), plugin_eval(from_bitmap, wi, wo), rtol=0.05, atol=1e-4)


def test_merl_plugin_fills_below_horizon_and_partly_missing_nodes():
    """What a MERL file may hold where nothing was measured: values at configurations below the horizon,
    missing samples (NaN, as MERLBRDF keeps them) and a node missing in one channel only (-1 in green). All are
    filled from the phi_d mean of the valid nodes, so a bivariate table stored that way still renders as the
    ``bivariate`` plugin does down to the horizon, and no lookup is negative. Kept as data, the below-horizon
    50 / sr put lookups near the horizon up to 400x off (measured); the one-channel gaps gave negative values;
    NaN turned into 0 on its way to the plugin would be read as a measured 0."""
    biv = lobe_table(width=0.2, diffuse=0.3, specular=2.0, n=8)
    table = np.array(biv.to_merl().table, np.float32)
    table[~geometric_mask()] = 50.0
    rng = np.random.default_rng(10)
    table[rng.integers(0, 90, 2000), rng.integers(0, 90, 2000), rng.integers(0, 180, 2000), 1] = -1.0
    table[rng.integers(0, 90, 2000), rng.integers(0, 90, 2000), rng.integers(0, 180, 2000)] = np.nan
    merl = mi.load_dict(merl_dict(MERLBRDF(table), "linear"))
    reference = mi.load_dict(bsdf_dict(biv))
    wi, wo = random_pairs(5000, seed=11, min_cos=0.0)
    got = plugin_eval(merl, wi, wo)
    assert np.all(got >= 0.0)
    np.testing.assert_allclose(got, plugin_eval(reference, wi, wo), rtol=0.05, atol=1e-4)


@pytest.mark.parametrize("plugin, suffix", [("bivariate", ".npz"), ("merl", ".binary")])
def test_a_relative_filename_is_found_beside_the_scene_file(tmp_path, monkeypatch, plugin, suffix):
    """Like Mitsuba's own plugins, a relative ``filename`` in a scene file is resolved against the scene
    file's folder, not the working directory."""
    biv = lobe_table(width=0.2, diffuse=0.3, specular=2.0, n=8)
    folder = tmp_path / "scene"
    folder.mkdir()
    biv.save(folder / "t.npz")
    biv.write_merl(folder / "t.binary")
    (folder / "scene.xml").write_text(
        '<scene version="3.0.0"><shape type="sphere"><bsdf type="%s">'
        '<string name="filename" value="t%s"/></bsdf></shape></scene>' % (plugin, suffix))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    scene = mi.load_file(str(folder / "scene.xml"))
    from_scene = scene.shapes()[0].bsdf()
    absolute = mi.load_dict({"type": plugin, "filename": str(folder / f"t{suffix}")})
    wi, wo = random_pairs(200, seed=6, min_cos=0.3)
    np.testing.assert_array_equal(plugin_eval(from_scene, wi, wo), plugin_eval(absolute, wi, wo))
    # A file of that name in the working directory is the one read (Mitsuba's resolver keeps the working
    # directory it saw at import, which may hold another file of the name).
    other = lobe_table(width=0.5, diffuse=0.6, specular=0.5, n=8)
    other.save(elsewhere / "t.npz")
    other.write_merl(elsewhere / "t.binary")
    here = mi.load_dict({"type": plugin, "filename": f"t{suffix}"})
    there = mi.load_dict({"type": plugin, "filename": str(elsewhere / f"t{suffix}")})
    np.testing.assert_array_equal(plugin_eval(here, wi, wo), plugin_eval(there, wi, wo))


# ------------------------------------------------------ parameters and AD

def sphere_scene(bsdf: dict, res: int = 16) -> mi.Scene:
    return mi.load_dict(sphere_scene_dict(bsdf, sun_sky_probe(), SphereCamera.create("orthographic", res), normals=False))


@pytest.mark.parametrize("plugin", ["bivariate", "merl"])
def test_parameter_update_changes_render(plugin):
    biv = lobe_table(width=0.3, diffuse=0.3, specular=1.0, n=8)
    bsdf = bsdf_dict(biv) if plugin == "bivariate" else merl_dict(biv.to_merl(), "nearest")
    scene = sphere_scene(bsdf)
    params = mi.traverse(scene)
    key = "sphere.bsdf.table"
    assert key in params and not (params.flags(key) & mi.ParamFlags.NonDifferentiable)
    before = np.array(mi.render(scene, spp=8, seed=3))
    params[key] = params[key] * 2.0
    params.update()
    doubled = np.array(mi.render(scene, spp=8, seed=3))
    # Uniform scaling leaves the sampling densities unchanged: exactly twice the image.
    np.testing.assert_allclose(doubled, 2.0 * before, rtol=1e-4, atol=1e-6)
    table = np.array(params[key])
    table[..., 0] = 0.0  # no red
    params[key] = mi.TensorXf(table)
    params.update()
    red_free = np.array(mi.render(scene, spp=8, seed=3))
    assert np.all(red_free[..., 0] == 0.0) and red_free[..., 1].sum() > 0.0


@pytest.mark.parametrize("plugin", ["bivariate", "merl"])
def test_a_table_update_renders_with_the_same_kernels(plugin):
    """An optimisation updates the table at every step, which moves the sampling mixture's weight p_c;
    the renders must reuse their compiled kernels. With p_c baked into the kernels as a literal, each
    update compiled them anew: analysis by synthesis (mi_bivariate.synthesis) went from 0.15 to 1.2-1.6 s
    an iteration once p_c left its clamp, and a kernel cache on disk hid it on reruns."""
    tables = [lobe_table(width=0.3, diffuse=0.3, specular=s, n=8) for s in (1.0, 2.0, 3.0)]
    bsdf = bsdf_dict(tables[0]) if plugin == "bivariate" else merl_dict(tables[0].to_merl(), "nearest")
    scene = sphere_scene(bsdf)
    params = mi.traverse(scene)
    key = "sphere.bsdf.table"
    weights, hashes = [], []
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for table in tables:
            value = table.table if plugin == "bivariate" else table.to_merl().table
            params[key] = mi.TensorXf(np.ascontiguousarray(value, dtype=np.float32))
            params.update()
            weights.append(scene.shapes()[0].bsdf().sampler.cosine_weight)
            dr.kernel_history()                           # clear it
            dr.eval(mi.render(scene, params, spp=4, seed=1))
            hashes.append(sorted(k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT))
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert len(set(weights)) == 3 and all(0.1 < w < 0.9 for w in weights), weights   # p_c moved, off its clamp
    # (the first render also runs one-off kernels: the second and third are compared)
    assert hashes[1] and hashes[2] == hashes[1]


@pytest.mark.parametrize("sampling", ["cosine", "table"])
def test_gradient_matches_finite_difference(sampling):
    biv = lobe_table(width=0.3, diffuse=0.3, specular=1.0, n=8)
    scene = sphere_scene({**bsdf_dict(biv), "sampling": sampling})
    params = mi.traverse(scene)
    key = "sphere.bsdf.table"
    params.keep(key)
    table0 = mi.TensorXf(params[key])
    rng = np.random.default_rng(5)
    delta = rng.uniform(0.0, 1.0, size=table0.shape).astype(np.float32) * np.array(biv.table)

    def loss(table: mi.TensorXf) -> float:
        params[key] = table
        params.update()
        return float(np.sum(np.array(mi.render(scene, params, spp=16, seed=7), np.float64)))

    dr.enable_grad(params[key])
    params.update()
    # The backward pass re-renders with seed_grad: the finite difference uses that seed.
    image = mi.render(scene, params, spp=16, seed=1, seed_grad=7)
    dr.backward(dr.sum(image, axis=None))
    grad = np.array(dr.grad(params[key]))
    assert np.abs(grad).sum() > 0.0
    directional = float(np.sum(grad * delta))
    h = 0.1
    with dr.suspend_grad():
        fd = (loss(table0 + h * mi.TensorXf(delta)) - loss(table0)) / h
    # The image is linear in the table. With cosine sampling the sampling does not
    # depend on the table, so the difference quotient is exact; with table
    # sampling the perturbed table is sampled differently (different noise).
    rtol = 1e-3 if sampling == "cosine" else 0.1
    assert directional == pytest.approx(fd, rel=rtol)


def test_merl_table_set_through_traverse_is_filled_like_a_loaded_one():
    """A MERL table with missing (NaN, negative) and below-horizon entries, set through ``mi.traverse``,
    renders as the same table loaded (no NaN pixel), and its valid entries keep their gradients."""
    a = to_merl(CookTorranceGGX(albedo_diffuse=0.2, specular=1.0, alpha=0.2, ior=1.5), dtype=np.float32)
    b = to_merl(CookTorranceGGX(albedo_diffuse=0.5, specular=1.0, alpha=0.3, ior=1.5), dtype=np.float32)
    raw = np.array(b.table, np.float32).reshape(90, 90, 180, 3)
    assert np.isnan(raw).any()
    raw[3, 40, 7] = -1.0  # MERL's own marker of a missing sample
    scene = sphere_scene(merl_dict(a, "nearest"), res=32)
    params = mi.traverse(scene)
    key = "sphere.bsdf.table"
    params[key] = mi.TensorXf(raw)
    params.update()
    updated = np.array(mi.render(scene, spp=16, seed=2))
    loaded = np.array(mi.render(sphere_scene(merl_dict(MERLBRDF(raw), "nearest"), res=32), spp=16, seed=2))
    assert np.all(np.isfinite(updated))
    np.testing.assert_allclose(updated, loaded, rtol=1e-5, atol=1e-7)
    # The filled nodes have no gradient, the valid ones have theirs (eval at random pairs, summed).
    table = mi.TensorXf(raw)
    dr.enable_grad(table)
    params[key] = table
    params.update()
    wi, wo = random_pairs(4000, seed=8)
    si = dr.zeros(mi.SurfaceInteraction3f, len(wi))
    si.wi = mi.Vector3f(*(mi.Float(wi[:, k].astype(np.float32)) for k in range(3)))
    value = scene.shapes()[0].bsdf().eval(mi.BSDFContext(), si, mi.Vector3f(*(mi.Float(wo[:, k].astype(np.float32))
                                                                            for k in range(3))))
    dr.backward(dr.sum(value, axis=None))
    grad = np.array(dr.grad(table))
    missing = ~((raw >= 0.0).all(-1) & geometric_mask())
    assert np.all(grad[missing] == 0.0) and np.count_nonzero(grad[~missing]) > 1000
    params[key] = mi.TensorXf(np.where(np.isnan(raw), np.inf, raw))
    with pytest.raises(InputError, match="infinite"):
        params.update()


def test_bivariate_table_set_through_traverse_is_checked():
    """A non-finite table set through ``mi.traverse`` is refused and the renders keep the last good table;
    negative values are rendered as 0, with a warning (a reflectance cannot be negative)."""
    biv = lobe_table(width=0.3, diffuse=0.3, specular=1.0, n=8)
    scene = sphere_scene(bsdf_dict(biv))
    params = mi.traverse(scene)
    key = "sphere.bsdf.table"
    good = np.array(params[key])
    before = np.array(mi.render(scene, spp=8, seed=3))
    table = good.copy()
    table[1, 2, 0] = np.nan
    params[key] = mi.TensorXf(table)
    with pytest.raises(InputError, match="NaN or infinite"):
        params.update()
    np.testing.assert_array_equal(np.array(mi.render(scene, spp=8, seed=3)), before)
    table = good.copy()
    table[:, :, 1] -= 0.5 * float(good[..., 1].max())  # some green values below 0
    params[key] = mi.TensorXf(table)
    with pytest.warns(InputWarning, match="negative values"):
        params.update()
    clamped = np.array(mi.render(scene, spp=8, seed=3))
    reference = np.array(mi.render(sphere_scene(bsdf_dict(BivariateBRDF(np.maximum(table, 0.0)))), spp=8, seed=3))
    assert np.all(clamped >= 0.0)
    np.testing.assert_allclose(clamped, reference, rtol=1e-5, atol=1e-7)
