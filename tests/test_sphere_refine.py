"""Refining the sphere by the image's shading (mi_bivariate.sphere_refine, recover --refine-sphere).

Truth: the geometry the image was rendered with. The material is a bivariate lobe, which the
bivariate table holds (up to the grid), rendered by the converged reference quadrature, so the
objective's minimum is the rendered sphere itself: started 0.5 px off in centre and 0.4 px in
radius, the refinement must come back to it (measured 0.02 px, +0.03 px); started on it, it must
stay; started 1.5 px off, further than the silhouette allows, it moves towards the sphere but does
not take what it found. (On 3D materials the bivariate model's own error moves the minimum by 0.1-0.35 px:
docs/recovery.md section 9.)
"""

from __future__ import annotations

import dataclasses
import json
import os
from types import SimpleNamespace

import numpy as np
import pytest

from mi_bivariate import analytic, probes, render, sphere_refine
from mi_bivariate.cli import main as cli_main
from mi_bivariate.errors import InputError, InputWarning
from mi_bivariate.geometry import Intrinsics, PerspectiveSphereGeometry, SphereGeometry
from mi_bivariate.images import write_exr
from mi_bivariate.recover import recover, recover_from_photo, refine_sphere_and_recover
from mi_bivariate.reference import render_reference
from mi_bivariate.sources import synthetic_environment

SMALL = dict(n_normals=1500, n_dirs=1500, grid=(16, 16))


@pytest.fixture(scope="module")
def probe():
    data = os.environ.get("MI_BIVARIATE_DATA")
    if data and os.path.isdir(data):
        return probes.shared_probe("grace_latlong_1k", data)
    return probes.Probe(synthetic_environment(seed=1), source="synthetic")


@pytest.fixture(scope="module")
def shot(probe):
    """A glossy bivariate lobe, 96 px, converged (the reference renderer), padded to 103 x 99 px so
    that the sphere sits off the image's centre with cx != cy (a swapped axis would show)."""
    truth = analytic.BivariateLobe(diffuse=(0.2, 0.15, 0.1), specular=(1.5, 1.5, 1.5), width=0.2, f0=1.0)
    rendered = render_reference(render.bsdf_dict(analytic.to_merl(truth)), probe, resolution=96, seed=1)
    g = rendered.geometry
    return SimpleNamespace(image=np.pad(rendered.image, ((3, 0), (7, 0), (0, 0))),
                           geometry=dataclasses.replace(g, cx=g.cx + 7.0, cy=g.cy + 3.0))


def _errors(geometry, truth):
    return float(np.hypot(geometry.cx - truth.cx, geometry.cy - truth.cy)), float(geometry.radius - truth.radius)


def _refine(image, probe, start, mask=None):
    first = recover(image, probe, start, noise=None, masks=mask, **SMALL)
    return sphere_refine.refine_sphere(image, probe, start, alphas=first.solution.alphas,
                                       winner=first.solution.winner, n_normals=SMALL["n_normals"],
                                       n_dirs=SMALL["n_dirs"], grid=SMALL["grid"], mask=mask)


@pytest.mark.parametrize("offset", [(0.4, -0.3, -0.4), (-0.3, 0.2, 0.45)], ids=["radius small", "radius large"])
def test_a_shifted_sphere_comes_back_to_the_rendered_one(shot, probe, offset):
    truth = shot.geometry
    dx, dy, dr = offset
    start = dataclasses.replace(truth, cx=truth.cx + dx, cy=truth.cy + dy, radius=truth.radius + dr)
    result = _refine(shot.image, probe, start)
    centre, radius = _errors(result.geometry, truth)
    assert result.accepted and result.geometry == result.found, result.summary()
    assert centre < 0.08 and abs(radius) < 0.08, result.summary()
    assert result.cost < 0.5 * result.cost_start
    assert 0.7 < result.shift_px <= sphere_refine.MAX_SHIFT_PX and "sphere refined by shading" in result.summary()


def test_masked_pixels_do_not_count(shot, probe):
    """A bright blot on the sphere (a reflection of something the probe lacks) pulls the refinement off;
    masked out, it does not."""
    truth = shot.geometry
    start = dataclasses.replace(truth, cx=truth.cx + 0.4, cy=truth.cy - 0.3, radius=truth.radius - 0.4)
    image = shot.image.copy()
    rows, cols = slice(int(truth.cy) - 30, int(truth.cy) - 10), slice(int(truth.cx) + 5, int(truth.cx) + 25)
    image[rows, cols] *= 4.0
    mask = np.ones(image.shape[:2], bool)
    mask[rows, cols] = False
    masked = _errors(_refine(image, probe, start, mask).geometry, truth)
    blotted = _errors(_refine(image, probe, start).geometry, truth)
    print(masked, blotted)
    assert masked[0] < 0.08 and abs(masked[1]) < 0.08, masked
    assert blotted[0] + abs(blotted[1]) > 2 * (masked[0] + abs(masked[1])) + 0.1, (blotted, masked)


def test_a_sphere_further_off_than_the_silhouette_allows_is_not_taken(shot, probe):
    truth = shot.geometry
    start = dataclasses.replace(truth, cx=truth.cx + 1.5)
    first = recover(shot.image, probe, start, noise=None, **SMALL)
    with pytest.warns(InputWarning, match="sphere not refined.*kept the fit") as seen:
        result = refine_sphere_and_recover(shot.image, probe, first, noise=None, **SMALL)
    refinement = result.sphere_refinement
    # The warning says why in one short line; the numbers are in the summary (printed once by the CLI).
    message = [str(w.message) for w in seen if "sphere not refined" in str(w.message)]
    assert len(message) == 1 and "->" not in message[0], message
    assert refinement.rejection() in result.summary() and "->" in result.summary()
    assert not refinement.accepted and refinement.geometry == start and result is first
    assert refinement.shift_px > sphere_refine.MAX_SHIFT_PX and _errors(refinement.found, truth)[0] < 0.5
    assert result.brdf.provenance["sphere_refinement"]["accepted"] is False


def test_a_refined_sphere_that_fits_worse_is_given_up(shot, probe, monkeypatch):
    """The refinement sees the image as the recovery does (the first recovery's camera-noise model is
    passed on), and a refined sphere whose recovery fits the image worse than the first one is not
    taken (forced here by a tolerance below 1: the refined sphere fits better)."""
    truth = shot.geometry
    start = dataclasses.replace(truth, cx=truth.cx + 0.3, cy=truth.cy - 0.2, radius=truth.radius - 0.3)
    noisy = shot.image + np.random.default_rng(0).normal(size=shot.image.shape).astype(np.float32) * 1e-3
    first = recover(noisy, probe, start, noise="auto", **SMALL)
    seen = {}
    refine = sphere_refine.refine_sphere
    monkeypatch.setattr(sphere_refine, "refine_sphere", lambda *a, **k: (seen.update(k), refine(*a, **k))[1])
    monkeypatch.setattr(sphere_refine, "MAX_RESIDUAL_RISE", 0.5)
    with pytest.warns(InputWarning, match="sphere not refined: the recovery under the refined sphere fits the image "
                                          "worse.*kept the fit"):
        result = refine_sphere_and_recover(noisy, probe, first, noise="auto", **SMALL)
    assert seen["noise"] == first.brdf.provenance["noise"][0] and seen["noise"] is not None
    assert result is first and not result.sphere_refinement.accepted
    assert result.sphere_refinement.geometry == start and _errors(result.sphere_refinement.found, truth)[0] < 0.15
    assert "fits the image worse" in result.brdf.provenance["sphere_refinement"]["rejection"]
    assert "refined recovery (given up)" in result.timings


def test_the_rendered_sphere_stays_put(shot, probe):
    result = _refine(shot.image, probe, shot.geometry)
    centre, radius = _errors(result.geometry, shot.geometry)
    assert centre < 0.08 and abs(radius) < 0.08, result.summary()
    assert result.cost <= result.cost_start


def test_only_an_orthographic_sphere_is_refined(shot, probe):
    k = Intrinsics.from_fov(96, 96, 40.0)
    with pytest.raises(InputError, match="orthographic"):
        sphere_refine.refine_sphere(shot.image, probe, PerspectiveSphereGeometry(k, [0.0, 0.0, -5.0], 1.0),
                                    alphas=(1e-3,) * 3, winner=("gloss",) * 3)
    with pytest.raises(InputError, match="orthographic"):  # refused before the fit
        recover_from_photo(shot.image, probe, intrinsics=(100.0, 100.0, 48.0, 48.0), refine_sphere=True)
    with pytest.raises(InputError, match="one value per channel"):
        sphere_refine.refine_sphere(shot.image, probe, shot.geometry, alphas=(1e-3,), winner=("gloss",) * 3)


def test_cli_recover_refine_sphere(tmp_path, shot, probe, capsys):
    """``recover --refine-sphere``: the refinement is printed, recorded in the table's provenance, and
    brings the fitted sphere closer to the rendered one; with --fov it is a one-line usage error."""
    write_exr(tmp_path / "photo.exr", shot.image)
    probe.save_exr(tmp_path / "probe.exr")
    argv = ["recover", str(tmp_path / "photo.exr"), "--probe", str(tmp_path / "probe.exr"), "--out",
            str(tmp_path / "x.npz"), "--normals", "1500", "--dirs", "1500", "--grid", "16", "16", "--noise", "none",
            "--no-report", "--refine-sphere"]
    assert cli_main(argv) == 0
    out = capsys.readouterr().out
    assert "refining the sphere" in out and "sphere refined by shading" in out, out
    with np.load(tmp_path / "x.npz") as z:
        meta = json.loads(str(z["meta"]))
    refinement = meta["provenance"]["sphere_refinement"]
    # The table records the photo and the sphere it was recovered under (the refined one).
    assert meta["provenance"]["photos"] == [str(tmp_path / "photo.exr")]
    recorded = meta["provenance"]["geometries"][0]
    assert recorded["type"] == "SphereGeometry"
    assert [recorded["cx"], recorded["cy"], recorded["radius"]] == refinement["refined"]
    truth = shot.geometry
    fitted = np.hypot(refinement["start"][0] - truth.cx, refinement["start"][1] - truth.cy)
    refined = np.hypot(refinement["refined"][0] - truth.cx, refinement["refined"][1] - truth.cy)
    assert refined < 0.08 and abs(refinement["refined"][2] - truth.radius) < 0.08, (refinement, fitted)
    assert refinement["cost"][1] <= refinement["cost"][0]
    assert cli_main(argv + ["--fov", "40"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("mi-bivariate: error: --refine-sphere: ") and "--fov" in err[0], err


def test_cli_refine_sphere_says_each_warning_once(tmp_path, shot, probe, capsys):
    """The recovery after the refinement repeats the first one's warnings about the photo (here: a grey
    photo under a coloured probe); the CLI says each once."""
    tinted = probes.Probe(probe.data * np.array([1.0, 0.8, 0.5], np.float32), to_world=probe.to_world, source="tinted")
    grey = np.repeat(shot.image.mean(axis=-1, keepdims=True), 3, axis=-1)
    write_exr(tmp_path / "grey.exr", grey)
    tinted.save_exr(tmp_path / "tinted.exr")
    argv = ["recover", str(tmp_path / "grey.exr"), "--probe", str(tmp_path / "tinted.exr"), "--out",
            str(tmp_path / "g.npz"), "--normals", "1500", "--dirs", "1500", "--grid", "16", "16", "--noise", "none",
            "--no-report", "--refine-sphere"]
    import warnings

    with warnings.catch_warnings(record=True) as seen:  # pytest records warnings before stderr sees them
        warnings.simplefilter("always")
        assert cli_main(argv) == 0
    lines = [str(w.message) for w in seen if issubclass(w.category, InputWarning)]
    assert sum("photo is grey" in line for line in lines) == 1, lines
    assert len(lines) == len(set(lines)), lines


def _small_sphere():
    """A 16 px sphere lit from above (shaded by hand: the contract tests below need no converged render),
    off the image's centre with cx != cy, under a probe bright above and dark below."""
    geometry = SphereGeometry(21.0, 19.0, 16.0)
    normals, mask = geometry.normals(44, 40)
    shading = 0.3 + 0.5 * np.clip(normals[..., 1:2], 0.0, None) + 0.2 * normals[..., 2:3]
    image = np.where(mask[..., None], shading, 0.0) * np.ones(3)
    sky = np.linspace(2.0, 0.2, 16)[:, None, None] * np.ones((16, 32, 3))
    return image, probes.Probe(sky.astype(np.float32)), geometry


TINY = dict(grid=(8, 8), n_normals=300, n_dirs=128)


def _cost_start(image, probe, geometry, alphas=(1e-3,) * 3, winner=("gloss",) * 3, **kwargs):
    return sphere_refine.refine_sphere(image, probe, geometry, alphas=alphas, winner=winner, max_evaluations=1,
                                       **TINY, **kwargs).cost_start


def test_the_objective_weighs_each_channel_by_its_own_prior_and_the_rows_by_their_sigmas():
    """The objective is the recovery's data term, channel by channel: on a grey image the three channels
    are the same problem, so giving channel 1 another alpha (or prior variant) makes the cost 2/3 of the
    first setting's plus 1/3 of the second's, exactly; the rows are weighed by their sigmas, so an image
    and its probe scaled by 50 cost the same, and a camera noise far above the signal costs next to nothing."""
    image, probe, geometry = _small_sphere()
    base = _cost_start(image, probe, geometry)
    smooth = _cost_start(image, probe, geometry, alphas=(1.0,) * 3)
    assert smooth > 1.05 * base
    assert _cost_start(image, probe, geometry, alphas=(1e-3, 1.0, 1e-3)) == pytest.approx(
        (2 * base + smooth) / 3, rel=1e-9)
    diffuse = _cost_start(image, probe, geometry, winner=("diffuse",) * 3)
    assert abs(diffuse - base) > 0.01 * base
    assert _cost_start(image, probe, geometry, winner=("gloss", "diffuse", "gloss")) == pytest.approx(
        (2 * base + diffuse) / 3, rel=1e-9)
    assert _cost_start(50.0 * image, probes.Probe(50.0 * probe.data), geometry) == pytest.approx(base, rel=1e-6)
    assert _cost_start(image, probe, geometry, noise=(0.0, 1e4)) < 1e-6 * base


def test_the_search_stops_at_its_budget_with_the_best_sphere_evaluated():
    """``max_evaluations`` evaluations and no more (the Jacobian's included); at the budget the best geometry
    evaluated is taken, with its cost, in the convention of least_squares' (half the sum of squares) as the
    starting cost is: one evaluation is the start itself; four (the start and three of the central-difference
    Jacobian's steps) found a lower cost than the start's."""
    image, probe, geometry = _small_sphere()
    for budget in (1, 4):
        result = sphere_refine.refine_sphere(image, probe, geometry, alphas=(1e-3,) * 3, winner=("gloss",) * 3,
                                             max_evaluations=budget, **TINY)
        assert result.evaluations == budget and result.status == f"stopped at the budget of {budget} evaluations"
        if budget == 1:
            assert result.cost == result.cost_start and result.found == geometry, result.summary()
        else:
            assert result.cost < result.cost_start and result.found != geometry, result.summary()
            assert result.accepted and result.shift_px < sphere_refine.MAX_SHIFT_PX


def test_a_sphere_too_small_to_refine_is_refused():
    """A 6 px sphere: the pixels that stay on any sphere within MAX_SHIFT_PX of it (at most
    1 - (1 + 0.71) / 6 of its radius from its centre) are too few to refine with; so are those of the
    16 px sphere that a mask leaves (a 6 x 6 window: the mask is the user's)."""
    image, probe, geometry = _small_sphere()
    with pytest.raises(InputError, match=r"only \d+ pixels to refine the sphere with"):
        sphere_refine.refine_sphere(image, probe, SphereGeometry(21.0, 19.0, 6.0), alphas=(1e-3,) * 3,
                                    winner=("gloss",) * 3, **TINY)
    mask = np.zeros(image.shape[:2], bool)
    mask[16:22, 18:24] = True
    with pytest.raises(InputError, match=r"only \d+ pixels to refine the sphere with"):
        sphere_refine.refine_sphere(image, probe, geometry, alphas=(1e-3,) * 3, winner=("gloss",) * 3, mask=mask,
                                    **TINY)


@pytest.mark.parametrize("budget, match", [(0, "must be at least 1, got 0"), (-3, "must be at least 1, got -3"),
                                           (2.5, "must be a whole number")])
def test_a_budget_of_no_evaluation_is_refused(budget, match):
    """The starting sphere's evaluation is the first: a budget below 1 ended in the search's internal
    stop signal (a bare sphere_refine._Budget from outside its handler), not an InputError."""
    image, probe, geometry = _small_sphere()
    with pytest.raises(InputError, match=f"^max_evaluations: {match}"):
        sphere_refine.refine_sphere(image, probe, geometry, alphas=(1e-3,) * 3, winner=("gloss",) * 3,
                                    max_evaluations=budget, **TINY)
