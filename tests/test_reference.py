"""The converged reference renderer (mi_bivariate.reference), camera noise and the named floors."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from mi_bivariate import analytic, metrics, noise, probes, reference, render
from mi_bivariate.bivariate import BivariateBRDF, exact_floor, grid_floor
from mi_bivariate.cli import main as cli_main
from mi_bivariate.errors import InputError
from mi_bivariate.merl import MERLBRDF
from mi_bivariate.sources import synthetic_environment

GLOSSY = analytic.CookTorranceGGX([0.25, 0.12, 0.05], 0.6, alpha=0.12, ior=1.5)
SMALL = (512, 1024, 512)


@pytest.fixture(scope="module")
def glossy_merl():
    return analytic.to_merl(GLOSSY, dtype=np.float32)


@pytest.fixture(scope="module")
def sky():
    return probes.Probe(synthetic_environment(seed=3), source="synthetic 3")


def test_lambertian_under_constant_light_is_exact():
    # Closed form: a Lambertian sphere under constant radiance L has radiance albedo * L everywhere.
    albedo = np.array([0.6, 0.4, 0.2])
    table = BivariateBRDF(np.broadcast_to(albedo / math.pi, (4, 4, 3)))
    light = probes.Probe.constant(2.0)
    expected = 2.0 * albedo
    # Cosine sampling alone: every sample is exactly albedo * L.
    out = reference.render_reference(table, light, resolution=16, directions=(256, 0, 0))
    np.testing.assert_allclose(out.image[out.mask], np.broadcast_to(expected, (out.mask.sum(), 3)), rtol=1e-5)
    # All three strategies (balance heuristic): unbiased, small quadrature error.
    mixed = reference.render_reference(table, light, resolution=16, directions=(512, 1024, 512))
    assert metrics.image_relative_rmse(mixed.image, out.image, out.mask) < 3e-3


def test_reference_noise_below_its_bound(glossy_merl, sky):
    # Two seeds are two independent quadratures; their difference / sqrt 2 is the per-image noise.
    q = reference.quadrature_noise(glossy_merl, sky, resolution=16, directions=SMALL, reference_factor=2.0)
    assert 0.0 < q["seed_rms"] < 0.005, q                  # two seeds are two quadratures: they differ
    assert q["vs_large"] < 0.005 * 1.5, q                 # no bias the two seeds share
    # The renderer is deterministic for a seed.
    a = reference.render_reference(glossy_merl, sky, resolution=12, seed=5, directions=(64, 128, 64))
    b = reference.render_reference(glossy_merl, sky, resolution=12, seed=5, directions=(64, 128, 64))
    np.testing.assert_array_equal(a.image, b.image)


def test_reference_noise_is_that_of_independent_seeds_in_any_number_of_chunks(glossy_merl, sky, monkeypatch):
    """The stated noise (two seeds' difference / sqrt 2) is the actual error: against a render with 16x the
    directions (whose own error is a fraction of it) each seed's image is off by about as much (measured ratio
    0.84-1.22 over seed pairs and sizes); seeds sharing random numbers would state a noise far below it. The
    per-pixel shifts travel with the pixels through the chunks: many chunks (7 pixels each, an uneven last
    one) give the one-chunk image bit for bit, so no chunk restarts or reuses another's random numbers."""
    small = (64, 128, 64)
    q = reference.quadrature_noise(glossy_merl, sky, resolution=16, directions=small, reference_factor=16.0)
    assert q["seed_rms"] > 0.0 and 0.7 < q["vs_large"] / q["seed_rms"] < 1.4, q
    whole = reference.render_reference(glossy_merl, sky, resolution=16, seed=0, directions=small)
    assert reference.CHUNK_LANES // max(small) >= 16 * 16                   # one chunk by default
    monkeypatch.setattr(reference, "CHUNK_LANES", 7 * max(small))
    parts = reference.render_reference(glossy_merl, sky, resolution=16, seed=0, directions=small)
    np.testing.assert_array_equal(parts.image, whole.image)


def test_reference_agrees_with_mitsuba(glossy_merl, sky):
    # The same BSDF plugin path-traced by Mitsuba (box filter: the reference averages 3 x 3 sub-pixels).
    res = 16
    ref = reference.render_reference(glossy_merl, sky, resolution=res, directions=SMALL, subpixels=3)
    shots = [render.render_sphere(glossy_merl, sky, resolution=res, spp=4096, seed=s) for s in (0, 1)]
    mask = ref.mask & shots[0].mask
    mean = 0.5 * (shots[0].image + shots[1].image)
    mitsuba_noise = metrics.image_relative_rmse(shots[0].image, shots[1].image, mask) / 2.0   # of the mean
    diff = metrics.image_relative_rmse(ref.image, mean, mask)
    assert diff < 1.5 * mitsuba_noise + 0.005, (diff, mitsuba_noise)
    # Summed over the sphere, Mitsuba's noise averages out: each channel agrees to 1%
    # (measured 0.1-0.3%), which a 3% brighter reference would fail.
    ratio = ref.image[mask].sum(axis=0) / mean[mask].sum(axis=0)
    np.testing.assert_allclose(ratio, 1.0, atol=0.01)
    assert np.all(np.abs(1.03 * ratio - 1.0) > 0.01)


def test_bad_quadrature_settings_are_refused_and_directions_scale_by_hand():
    """No strategy, a negative count, a one-pixel image or no sub-pixel: InputError before any render.
    ``scaled_directions`` rounds, keeps a strategy that is on at 1 direction at least and one that is off at 0."""
    table = BivariateBRDF(np.full((4, 4, 3), 0.1))
    light = probes.Probe.constant(1.0)
    for kwargs in (dict(directions=(0, 0, 0)), dict(directions=(8, -1, 8)), dict(directions=(8, 8)),
                   dict(resolution=1), dict(subpixels=0)):
        with pytest.raises(InputError):
            reference.render_reference(table, light, **{"resolution": 4, "directions": (4, 4, 4), **kwargs})
    assert reference.scaled_directions(1e-4) == (1, 1, 1)
    assert reference.scaled_directions(0.3, (10, 0, 5)) == (3, 0, 2)   # 1.5 rounds to 2; off stays off
    assert reference.scaled_directions(2.0) == tuple(2 * k for k in reference.DEFAULT_DIRECTIONS)


def test_camera_noise_model():
    image = np.zeros((60, 60, 3), np.float32)
    image[5:55, 5:55] = 2.0
    noisy = noise.add_camera_noise(image, 0.05, seed=3)
    a, b = noise.noise_parameters(image, 0.05)
    assert a == pytest.approx(0.05 ** 2 * 2.0) and b == pytest.approx((0.1 * 0.05 * 2.0) ** 2)
    inside = noisy[5:55, 5:55] - 2.0
    assert inside.std() == pytest.approx(math.sqrt(a * 2.0 + b), rel=0.05)   # 7500 samples: ~1% error
    assert abs(inside.mean()) < 0.003
    assert np.all(noisy[:5] == 0.0)                        # background untouched
    np.testing.assert_array_equal(noisy, noise.add_camera_noise(image, 0.05, seed=3))
    assert not np.array_equal(noisy, noise.add_camera_noise(image, 0.05, seed=4))
    np.testing.assert_array_equal(noise.add_camera_noise(image, 0.0), image)


# ------------------------------------------------------------------ floors

def test_exact_floor_of_a_bivariate_brdf_is_zero():
    rng = np.random.default_rng(0)
    table = BivariateBRDF(rng.uniform(0.05, 3.0, (91, 91, 3)))
    merl = table.to_merl()
    assert exact_floor(merl) < 1e-6
    # Read back on MERL's own st nodes (91 x 91): exact; on a coarser grid interpolation error appears.
    assert grid_floor(merl, 91, 91) < 1e-6
    assert grid_floor(merl, 8, 8) > 0.1


def _independent_exact_floor(table: np.ndarray) -> float:
    """Eq. 1 of the phi_d average, from scratch: build wi and wo for every MERL node and average over
    the phi_d whose directions are both above the horizon (plain numpy, no package code)."""
    n = np.arange(90)
    th = (n / 90.0) ** 2 * (math.pi / 2)
    td = n / 90.0 * (math.pi / 2)
    pd = np.arange(180) / 180.0 * math.pi
    TH, TD, PD = np.meshgrid(th, td, pd, indexing="ij")
    # Difference vector d = (sin td cos pd, sin td sin pd, cos td), rotated about y by theta_h (phi_h = 0).
    dx, dz = np.sin(TD) * np.cos(PD), np.cos(TD)
    wi_z = -np.sin(TH) * dx + np.cos(TH) * dz
    wo_z = np.sin(TH) * dx + np.cos(TH) * dz          # wo = 2 (wi.h) h - wi: wi mirrored about h
    ok = (wi_z > 0) & (wo_z > 0) & np.all(np.isfinite(table), axis=-1)
    f = np.where(ok[..., None], table, 0.0)
    mean = f.sum(axis=2) / np.maximum(ok.sum(axis=2), 1)[..., None]
    cells = ok[..., None] & (table > 0)
    rel = np.where(cells, (f - mean[:, :, None, :]) / np.where(cells, table, 1.0), 0.0)
    return float(np.sqrt((rel ** 2).sum() / cells.sum()))


def test_reduce_prints_exact_floor_matching_independent_computation(tmp_path, capsys, glossy_merl):
    path = tmp_path / "glossy.binary"
    MERLBRDF(np.asarray(glossy_merl.table, np.float64), name="glossy").write(path)
    assert cli_main(["reduce", str(path), "--out", str(tmp_path / "glossy.npz")]) == 0
    out = capsys.readouterr().out
    printed = float(re.search(r"exact floor[^:]*: ([0-9.]+)", out).group(1))
    grid = float(re.search(r"grid floor[^:]*: ([0-9.]+)", out).group(1))
    expected = _independent_exact_floor(MERLBRDF.read(path).table)
    assert expected > 0.01                                  # a real, non-trivial floor
    assert printed == pytest.approx(expected, rel=0.05)
    assert grid > printed                                   # the 32 x 32 grid adds interpolation error
