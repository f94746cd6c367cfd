"""mi_bivariate.synthesis: the analysis-by-synthesis baseline optimises what it should."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import independent_relight_floor

from mi_bivariate import render, synthesis
from mi_bivariate.bivariate import BivariateBRDF
from mi_bivariate.errors import InputError, InputWarning
from mi_bivariate.probes import Probe


def test_lambertian_start_is_the_best_constant():
    rng = np.random.default_rng(0)
    L = rng.uniform(0.0, 1.0, (50, 16, 3))
    c = np.array([0.3, 0.2, 0.1])
    y = L.sum(axis=1) * c  # exactly a constant table
    np.testing.assert_allclose(synthesis.lambertian_start(L, y), c, rtol=1e-12)
    noisy = y + rng.normal(0.0, 0.01, y.shape)
    # The least-squares constant: compare with numpy's lstsq per channel.
    want = [np.linalg.lstsq(L[:, :, k].sum(axis=1, keepdims=True), noisy[:, k], rcond=None)[0][0] for k in range(3)]
    np.testing.assert_allclose(synthesis.lambertian_start(L, noisy), want, rtol=1e-10)


def test_adam_through_prb_recovers_a_scaled_table():
    """From a start 2x too bright, the loss falls and the table moves towards the truth."""
    from mi_bivariate.variants import ensure_variant

    ensure_variant()
    probe = Probe.constant(1.0, 16)
    truth = np.broadcast_to(np.array([0.5, 0.3, 0.2]) / np.pi, (6, 6, 3)).astype(np.float32)
    shot = render.render_sphere(render.bsdf_dict(BivariateBRDF(truth)), probe, resolution=24, spp=64, seed=0)
    start = 2.0 * truth
    settings = synthesis.SynthesisSettings(spp=8, learning_rate=0.05, seed=3)
    run = synthesis.optimise_table(shot.image, shot.mask, probe, start, settings, budget_s=1e9, max_iterations=30)
    assert run["iterations"] == 30
    assert np.mean(run["losses"][-5:]) < 0.2 * np.mean(run["losses"][:3])
    ratio = run["table"].mean(axis=(0, 1)) / truth[0, 0]
    assert np.all(np.abs(ratio - 1.0) < 0.5 * np.abs(2.0 - 1.0)), ratio  # at least halfway home
    again = synthesis.optimise_table(shot.image, shot.mask, probe, start, settings, budget_s=1e9, max_iterations=30)
    # Seeded; the backward pass accumulates table gradients with atomic adds over threads, so
    # the sums are reproducible to float32 rounding, not bit for bit.
    np.testing.assert_allclose(again["table"], run["table"], rtol=1e-3)


def test_optimise_table_refuses_or_drops_what_it_cannot_fit():
    """A NaN pixel on the sphere is dropped from the loss (as the linear route drops it) instead of
    turning every loss into NaN and freezing the table; images and masks it cannot use, and a zero
    ``eval_every``, are refused with one readable line, before any render."""
    from mi_bivariate.variants import ensure_variant

    ensure_variant()
    probe = Probe.constant(1.0, 16)
    truth = np.broadcast_to(np.array([0.5, 0.3, 0.2]) / np.pi, (4, 4, 3)).astype(np.float32)
    shot = render.render_sphere(render.bsdf_dict(BivariateBRDF(truth)), probe, resolution=16, spp=8, seed=0)
    settings = synthesis.SynthesisSettings(spp=4, seed=3)

    def run(image=shot.image, mask=shot.mask, **kwargs):
        return synthesis.optimise_table(image, mask, probe, 2.0 * truth, settings, budget_s=1e9, max_iterations=3,
                                        **kwargs)

    image = shot.image.copy()
    image[8, 8, 0] = np.nan
    assert shot.mask[8, 8]
    with pytest.warns(InputWarning, match="1 sphere pixel"):
        dropped = run(image)
    without = shot.mask.copy()
    without[8, 8] = False
    kept = run(mask=without)                              # the same pixel left out by the caller
    assert np.all(np.isfinite(dropped["losses"])) and not np.allclose(dropped["table"], 2.0 * truth)
    np.testing.assert_allclose(dropped["losses"], kept["losses"], rtol=1e-5)
    for kwargs, message in [(dict(mask=np.zeros_like(shot.mask)), "no sphere pixel"),
                            (dict(mask=shot.mask[:10]), "mask has shape"),
                            (dict(image=shot.image[..., 0]), "RGB image"),
                            (dict(image=shot.image[:, :12], mask=shot.mask[:, :12]), "square"),
                            (dict(image=np.zeros_like(shot.image)), "black"),
                            (dict(eval_every=0), "eval_every")]:
        with pytest.raises(InputError, match=message):
            run(**kwargs)


def _sky_shot():
    """A 16 px render of a constant table under a sky with a gradient (so that each seed's render differs), the
    sizes of test_optimise_table_refuses_or_drops_what_it_cannot_fit's (its compiled kernels serve)."""
    from mi_bivariate.variants import ensure_variant

    ensure_variant()
    theta = (np.arange(8) + 0.5)[:, None, None] / 8
    probe = Probe((0.2 + 2.0 * (1.0 - theta) * np.ones((8, 16, 3))).astype(np.float32), source="sky")
    truth = np.broadcast_to(np.array([0.5, 0.3, 0.2]) / np.pi, (4, 4, 3)).astype(np.float32)
    return probe, truth, render.render_sphere(render.bsdf_dict(BivariateBRDF(truth)), probe, resolution=16,
                                              spp=64, seed=0)


def test_optimise_table_loss_is_relative_each_iteration_has_its_seed_and_the_last_is_checked():
    """Closed form: twice the true table renders twice the image, so the first loss (mean squared error over
    the image's mean square) is ~1 (plus the renders' own noise). With a step too small to move the table, each iteration's render still
    differs (its own seed); ``on_checkpoint`` sees every ``eval_every``-th iteration and the last. A sphere
    pixel that is 0 is a pixel like any other."""
    probe, truth, shot = _sky_shot()
    image = shot.image.copy()
    image[8, 8] = 0.0
    assert shot.mask[8, 8]
    seen = []
    settings = synthesis.SynthesisSettings(spp=4, learning_rate=1e-9, smoothness=0.0, seed=3)
    run = synthesis.optimise_table(image, shot.mask, probe, 2.0 * truth, settings, budget_s=1e9, max_iterations=3,
                                   eval_every=2, on_checkpoint=lambda it, clock, loss, table: seen.append(it))
    assert seen == [2, 3]
    assert 0.9 < run["losses"][0] < 1.4                  # 1 plus the 4 spp renders' own noise (1.21 measured)
    assert len(set(run["losses"])) == 3


def test_optimise_table_keeps_log_f_within_its_bounds():
    """A start above ``exp(log_bounds[1])`` is brought down to it after the first step."""
    probe, truth, shot = _sky_shot()
    hi = float(np.log(0.2))
    settings = synthesis.SynthesisSettings(spp=4, seed=3, log_bounds=(-14.0, hi))
    run = synthesis.optimise_table(shot.image, shot.mask, probe, 2.0 * truth, settings, budget_s=1e9,
                                   max_iterations=1)
    assert 2.0 * truth.max() > 0.3 and run["table"].max() <= 0.2 * (1 + 1e-6)


@pytest.mark.parametrize("field, value, message", [
    ("spp", 0, "spp"), ("spp", 2.5, "spp"), ("learning_rate", -0.05, "learning_rate"),
    ("learning_rate", float("nan"), "learning_rate"), ("smoothness", -1e-3, "smoothness"),
    ("max_depth", 1, "max_depth"), ("log_bounds", (9.0, -14.0), "log_bounds"), ("sampling", "uniform", "sampling")])
def test_synthesis_settings_refuse_what_the_optimiser_cannot_use(field, value, message):
    """spp 0 rendered at Mitsuba's default sampler count (4) while the record said 0; a negative step
    climbs the loss; max_depth 1 renders no reflection (a black sphere, zero gradients): all refused."""
    with pytest.raises(InputError, match=message):
        synthesis.SynthesisSettings(**{field: value})
    synthesis.SynthesisSettings()                         # the defaults are valid


def test_time_to_error_picks_the_fastest_run_that_reaches_the_error():
    points = [{"time_s": 0.3, "relight": 0.20}, {"time_s": 0.5, "relight": 0.10},
              {"time_s": 1.0, "relight": 0.06}, {"time_s": 0.4, "relight": 0.12}]
    assert synthesis.time_to_error(points, 0.12)["time_s"] == 0.4   # reached exactly counts
    assert synthesis.time_to_error(points, 0.11)["time_s"] == 0.5
    assert synthesis.time_to_error(points, 0.2)["time_s"] == 0.3
    assert synthesis.time_to_error(points, 0.05) is None
    assert synthesis.time_to_error([], 1.0) is None


def test_ladder_sizes_are_cheaper_than_the_configuration_and_fixed_fractions_of_it():
    assert synthesis.ladder_sizes(8000, 8000) == [(1000, 1000), (2000, 2000), (4000, 4000)]
    # The evaluation's quick config: rungs are floored at LADDER_MIN and never above the config.
    assert synthesis.ladder_sizes(1000, 3000) == [(250, 375), (250, 750), (500, 1500)]
    assert synthesis.ladder_sizes(250, 250) == []
    assert synthesis.ladder_sizes(8000, 8000, ()) == []
    assert synthesis.ladder_sizes(100, 8000) == []        # LADDER_MIN normals would be more than the config's
    for m, k in synthesis.ladder_sizes(300, 20000):
        assert m <= 300 and k <= 20000


def test_ladder_grids_are_coarser_than_the_configuration_and_every_rung_is_listed_once():
    assert synthesis.ladder_grids((32, 32)) == [(16, 16)]
    assert synthesis.ladder_grids((32, 24), (1 / 2, 1 / 4)) == [(16, 12), (8, 6)]
    assert synthesis.ladder_grids((6, 6)) == [(4, 4)]        # floored at LADDER_GRID_MIN ...
    assert synthesis.ladder_grids((4, 4)) == []               # ... and never the configuration's own
    assert synthesis.ladder_grids((3, 40)) == []              # not coarser on both sides
    assert synthesis.ladder_grids((32, 32), ()) == []
    rungs = synthesis.ladder_rungs(8000, 8000, (32, 32))
    sizes = [(1000, 1000), (2000, 2000), (4000, 4000)]
    assert rungs == [(m, k, (32, 32)) for m, k in sizes] + [(m, k, (16, 16)) for m, k in sizes + [(8000, 8000)]]
    assert synthesis.ladder_rungs(8000, 8000, (32, 32), (), ()) == []
    assert synthesis.ladder_rungs(8000, 8000, (32, 32), ()) == [(8000, 8000, (16, 16))]
    assert synthesis.rung_label({"n_normals": 1000, "n_dirs": 2000, "grid": [16, 12]}) == "M 1000, K 2000, 16 x 12"
    assert synthesis.rung_label({"n_normals": 1000, "n_dirs": 2000}) == "M 1000, K 2000"   # an older record


def test_relight_error_scores_with_the_evaluations_renderer_against_closed_forms():
    """White furnace: a Lambertian table rho / pi under a constant probe of radiance 1 renders as
    exactly rho at every pixel, so twice the table is 100% off and the truth itself 0%; the
    converged renderer's own noise is far below the errors it scores (path tracing at these spp is not)."""
    from mi_bivariate.evaluate.config import EvalConfig
    from mi_bivariate.evaluate.renders import Renderer
    from mi_bivariate.sources import MaterialSpec
    from mi_bivariate.variants import ensure_variant

    ensure_variant()
    config = EvalConfig.quick(shared_data=False)
    renderer = Renderer(config, MaterialSpec("furnace", "analytic", "lambert"), cache_dir=None)
    probe = Probe.constant(1.0, 16)
    rho = np.array([0.5, 0.3, 0.2])
    table = np.broadcast_to(rho / np.pi, (6, 6, 3)).astype(np.float32)
    truth = renderer.render(BivariateBRDF(table), probe, "constant", 24, 1, config.novel_spp)
    pixels = truth.image[truth.mask]                      # the quick config's few directions: ~0.1% per pixel
    np.testing.assert_allclose(pixels, np.broadcast_to(rho, pixels.shape), rtol=1e-2)
    np.testing.assert_allclose(pixels.mean(axis=0), rho, rtol=1e-3)
    assert synthesis.relight_error(table, renderer, probe, "constant", truth, 1) < 1e-6
    assert abs(synthesis.relight_error(2.0 * table, renderer, probe, "constant", truth, 1) - 1.0) < 1e-3
    noise = synthesis.render_noise(table, renderer, probe, "constant", truth, (5, 6))
    assert noise < 2e-3
    path = Renderer(EvalConfig.quick(shared_data=False, renderer="path"), MaterialSpec("f", "analytic", "l"), None)
    assert synthesis.render_noise(table, path, probe, "constant", truth, (5, 6)) > 5 * noise


def test_linear_reaches_takes_the_fastest_point_that_is_as_good_as_abs_best():
    ladder = [{"time_s": 0.3, "relight": 0.09}, {"time_s": 0.4, "relight": 0.05}]
    default = {"time_s": 1.0, "relight": 0.04}
    assert synthesis.linear_reaches(ladder + [default], 0.1, 30.0) == (ladder[0], pytest.approx(100.0))
    assert synthesis.linear_reaches(ladder + [default], 0.06, 30.0) == (ladder[1], pytest.approx(75.0))
    # Only the default run is good enough: it is the one timed against AbS.
    assert synthesis.linear_reaches(ladder + [default], 0.045, 30.0) == (default, pytest.approx(30.0))
    assert synthesis.linear_reaches(ladder + [default], 0.01, 30.0) == (None, None)


def test_no_speedup_is_claimed_when_abs_never_beats_its_start(monkeypatch):
    """AbS's best at its start (time 0) gives no ratio, not "0x": the linear route was not infinitely
    slower, AbS just never improved (seen with --quick on blue-acrylic)."""
    assert synthesis.linear_reaches([{"time_s": 0.3, "relight": 0.09}], 0.1, 0.0) == (
        {"time_s": 0.3, "relight": 0.09}, None)

    def no_progress(image, mask, probe, start, settings, budget_s=60.0, max_iterations=100000, eval_every=10,
                    on_checkpoint=None):
        if on_checkpoint is not None:
            on_checkpoint(10, 1.0, 0.5, 4.0 * np.asarray(start))   # worse than the start
        return {"iterations": 10, "time_s": 1.0, "losses": [0.5] * 10, "table": 4.0 * np.asarray(start)}

    monkeypatch.setattr(synthesis, "optimise_table", no_progress)
    config = _tiny_abs_config(monkeypatch)
    r = synthesis.analysis_by_synthesis("ggx:diffuse=0.2,specular=0.5,alpha=0.2", "synthetic:1", config=config,
                                        linear_ladder=(), ladder_grid_fractions=(), ladder_repeats=1)
    assert r["abs"]["best_relight_iteration"] == 0 and r["linear"]["relight"] <= r["abs"]["best_relight"]
    assert r["speedup"] is None and r["ladder_speedup"] is None
    assert r["linear_to_abs_best"]["n_normals"] == 300      # the linear run that reaches it is still named


def _tiny_abs_config(monkeypatch):
    """A small configuration for analysis_by_synthesis with optimise_table stood in, and no priors learnt."""
    from mi_bivariate.evaluate.config import EvalConfig

    monkeypatch.setattr(synthesis, "choose_priors", lambda task: (None, None, "test: no basis prior"))
    return EvalConfig(input_probes=("synthetic:1",), novel_probes=("synthetic:7",), resolution=32, spp=8,
                      novel_spp=4, novel_resolution=16, n_normals=300, n_dirs=1000, grid=(8, 8), baselines=(),
                      reference_directions=(256, 512, 256))


def test_abs_clock_excludes_kernel_compilation_as_the_linear_routes_does(monkeypatch):
    """The linear route is timed after a warm-up run (its kernels compiled); AbS is timed alike. Here a
    stand-in for optimise_table whose first call in the process pays 100 s of "compilation" in its first
    iteration, as the real one pays 2.4-5 s with a cold Dr.Jit kernel cache (0.6 s an iteration after)."""
    calls = []

    def optimise_table(image, mask, probe, start, settings, budget_s=60.0, max_iterations=100000, eval_every=10,
                       on_checkpoint=None):
        compile_s = 100.0 if not calls else 0.0
        calls.append(max_iterations)
        clock, it = 0.0, 0
        while it < max_iterations:
            clock += 0.5 + (compile_s if it == 0 else 0.0)
            it += 1
            done = clock >= budget_s or it >= max_iterations
            if on_checkpoint is not None and (it % eval_every == 0 or done):
                on_checkpoint(it, clock, 0.5, np.asarray(start))
            if done:
                break
        return {"iterations": it, "time_s": clock, "losses": [0.5] * it, "table": np.asarray(start)}

    monkeypatch.setattr(synthesis, "optimise_table", optimise_table)
    config = _tiny_abs_config(monkeypatch)
    r = synthesis.analysis_by_synthesis("ggx:diffuse=0.2,specular=0.5,alpha=0.2", "synthetic:1", config=config,
                                        linear_ladder=(), ladder_grid_fractions=(), ladder_repeats=1, budget_s=5.0, eval_every=2)
    assert r["abs"]["iterations"] == 10 and r["abs"]["time_s"] == pytest.approx(5.0)
    assert [t["time_s"] for t in r["trace"]] == pytest.approx([0.0, 1.0, 2.0, 3.0, 4.0, 5.0])


def test_scoring_ignores_pixels_outside_the_mask_and_its_noise_is_the_reference_renderers():
    """Outside the mask (pixels the sphere only partly covers, the background) nothing is scored; the
    noise is :func:`mi_bivariate.reference.quadrature_noise`'s, an independent implementation."""
    from mi_bivariate import reference
    from mi_bivariate.evaluate.config import EvalConfig
    from mi_bivariate.evaluate.renders import Renderer, Shot
    from mi_bivariate.sources import MaterialSpec
    from mi_bivariate.variants import ensure_variant

    ensure_variant()
    config = EvalConfig.quick(shared_data=False)
    renderer = Renderer(config, MaterialSpec("glossy", "analytic", "ggx"), cache_dir=None)
    probe = Probe.constant([1.0, 0.8, 0.6], 16)
    t, s = np.meshgrid(np.linspace(0, 1, 8), np.linspace(0, 1, 8), indexing="ij")
    table = (np.exp(-8.0 * t)[..., None] * [2.0, 1.5, 1.0] + 0.1 * (1 + s[..., None])).astype(np.float32)
    truth = renderer.render(BivariateBRDF(table), probe, "constant", 24, 1, config.novel_spp)
    polluted = Shot(np.where(truth.mask[..., None], truth.image, 1e3).astype(np.float32), truth.mask, truth.geometry)
    assert (~truth.mask).any()
    assert synthesis.relight_error(table, renderer, probe, "constant", polluted, 1) < 1e-6
    noise = synthesis.render_noise(table, renderer, probe, "constant", truth, (5, 6))
    want = reference.quadrature_noise(BivariateBRDF(table), probe, resolution=24,
                                      directions=config.reference_directions, seeds=(5, 6))["seed_rms"]
    assert noise > 0 and noise == pytest.approx(want, rel=1e-6)


def test_analysis_by_synthesis_times_every_linear_point_alike_and_scores_at_the_evaluations_seed(monkeypatch):
    """One warm-up run at the config's sizes, then 3 timed runs of it and of each ladder rung, the
    medians of known stage times; the novel probe rendered at the seed the evaluation gives it
    (the config's second novel probe: seed + 2), checked against an independent render."""
    import dataclasses

    from mi_bivariate.evaluate.config import EvalConfig

    real, calls, chosen, used = synthesis.recover, [], [], []

    def recover(*args, **kwargs):
        i = len(calls)
        calls.append((kwargs["n_normals"], kwargs["n_dirs"], tuple(kwargs["grid"])))
        used.append((kwargs["prior"], kwargs["basis_prior"]))
        rec = real(*args, **{**kwargs, "prior": None})      # the stand-in priors below are markers only
        rec.timings = {stage: (i + 1) * (j + 1) * 1e-3 for j, stage in enumerate(synthesis.LINEAR_STAGES)}
        return rec

    def choose_priors(task):                              # where the evaluation's choice comes from
        assert task.material.label.startswith("ggx:")
        # The configuration itself, or (for the ladder's coarser grid) it on that grid.
        assert task.config is config or task.config == dataclasses.replace(config, grid=(4, 4))
        # A marker per grid as the smoothness prior (recover gets None), no basis prior (recover's default: "default").
        chosen.append((object(), None, f"test: no basis prior, {task.config.grid}"))
        return chosen[-1]

    monkeypatch.setattr(synthesis, "recover", recover)
    monkeypatch.setattr(synthesis, "choose_priors", choose_priors)
    config = EvalConfig(input_probes=("synthetic:1",), novel_probes=("synthetic:7", "synthetic:3"), resolution=32,
                        spp=8, novel_spp=4, novel_resolution=16, n_normals=300, n_dirs=1000, grid=(8, 8),
                        baselines=(), reference_directions=(256, 512, 256))
    material = "ggx:diffuse=0.2,specular=0.5,alpha=0.2"
    r = synthesis.analysis_by_synthesis(material, "synthetic:1", config=config, novel_probe="synthetic:3",
                                        budget_s=0.3, eval_every=5, spp=4)
    rungs = synthesis.ladder_rungs(300, 1000, (8, 8))
    fine = [rung for rung in rungs if rung[2] == (8, 8)]
    coarse = [rung for rung in rungs if rung[2] == (4, 4)]
    assert len(fine) == 2 and coarse == [(m, k, (4, 4)) for m, k, _ in fine] + [(300, 1000, (4, 4))]
    # A warm-up on each grid: at the config's sizes on its own, at the first coarse rung's on the coarser.
    assert calls == ([(300, 1000, (8, 8))] * 4 + [rung for rung in fine for _ in range(3)]
                     + [coarse[0]] + [rung for rung in coarse for _ in range(3)])
    # Every linear run used the priors chosen for this material, on its grid, as the evaluation chooses them.
    assert [c[2] for c in chosen] == ["test: no basis prior, (8, 8)", "test: no basis prior, (4, 4)"]
    for call, (prior, basis_prior) in zip(calls, used, strict=True):   # each run got its own grid's priors
        assert prior is chosen[0 if call[2] == (8, 8) else 1][0] and basis_prior is None
    assert r["linear"]["prior"] == chosen[0][2]
    assert [p.get("prior") for p in r["linear_ladder"]] == [None] * len(fine) + [chosen[1][2]] * len(coarse)
    # The config's sizes: calls 1-3 (call 0 is the warm-up); the median of (2, 3, 4) x each stage's unit.
    want = {stage: 3 * (j + 1) * 1e-3 for j, stage in enumerate(synthesis.LINEAR_STAGES)}
    assert r["linear"]["stages"] == pytest.approx(want) and r["linear"]["time_s"] == pytest.approx(sum(want.values()))
    firsts = [4 + 3 * k for k in range(len(fine))] + [4 + 3 * len(fine) + 1 + 3 * k for k in range(len(coarse))]
    assert [(p["n_normals"], p["n_dirs"], tuple(p["grid"])) for p in r["linear_ladder"]] == rungs
    for first, point in zip(firsts, r["linear_ladder"], strict=True):   # a rung's calls: first .. first + 2
        assert point["time_s"] == pytest.approx((first + 2) * sum(j + 1 for j in range(len(want))) * 1e-3)

    floors = [independent_relight_floor(config, material, "synthetic:3", seed, 16)
              for seed in (config.seed + 2, config.seed + 1)]
    assert abs(floors[0] - floors[1]) > 1e-6 * floors[0]   # the seed shows in the floor ...
    assert r["relight_floor"] == pytest.approx(floors[0], rel=1e-7)   # ... and it is the evaluation's
    assert r["abs"]["best_relight"] == min(t["relight"] for t in r["trace"])


def test_synthesis_settings_accept_the_edges_of_what_the_optimiser_can_use():
    """No smoothness (0), unlimited depth (-1) are settings; infinite steps, weights or bounds and bounds that
    are not numbers are not."""
    synthesis.SynthesisSettings(smoothness=0.0, max_depth=-1, spp=1)
    for field, value in [("learning_rate", float("inf")), ("smoothness", float("inf")),
                         ("log_bounds", (-float("inf"), 9.0)), ("log_bounds", ("a", "b")), ("max_depth", -2)]:
        with pytest.raises(InputError, match=field):
            synthesis.SynthesisSettings(**{field: value})


def test_lambertian_start_is_never_negative():
    """An image anti-correlated with the all-ones prediction has a negative least-squares constant: the start
    is 0 there (a BRDF is >= 0), the least-squares value elsewhere."""
    L = np.random.default_rng(2).uniform(0.0, 1.0, (40, 9, 3))
    y = L.sum(axis=1) * np.array([0.3, 0.2, 0.1])
    y[:, 1] *= -1.0
    np.testing.assert_allclose(synthesis.lambertian_start(L, y), [0.3, 0.0, 0.1], rtol=1e-12, atol=0)


def test_a_linear_points_time_is_the_median_of_its_runs(monkeypatch):
    """``linear_run``'s time is the median of its runs' stage sums (a slow outlier run does not move it)."""
    sums = iter([1.0, 2.0, 10.0])

    def recover(*args, **kwargs):
        total = next(sums)
        return type("Rec", (), {"timings": {stage: total / len(synthesis.LINEAR_STAGES)
                                            for stage in synthesis.LINEAR_STAGES}})()

    monkeypatch.setattr(synthesis, "recover", recover)
    shot = type("Shot", (), {"image": None, "geometry": None})()
    config = type("Config", (), {"grid": (8, 8), "alpha": None, "seed": 0})()
    _, point = synthesis.linear_run(shot, None, config, 300, 1000, 3)
    assert point["times_s"] == pytest.approx([1.0, 2.0, 10.0]) and point["time_s"] == pytest.approx(2.0)


def test_linear_reaches_gives_no_ratio_for_a_linear_run_of_no_time():
    """A linear run timed at 0 s reaches AbS's best but gives no speed ratio (not a division by zero)."""
    point = {"time_s": 0.0, "relight": 0.05}
    assert synthesis.linear_reaches([point], 0.1, 3.0) == (point, None)


def test_scored_tables_are_cleaned_of_nan_and_negative_values():
    """``bivariate_brdf`` (what AbS's checkpoints are scored as): NaN and negative nodes become 0."""
    table = np.full((4, 4, 3), 0.2)
    table[0, 0, 0], table[1, 2, 1] = np.nan, -0.5
    got = synthesis.bivariate_brdf(table).table
    assert np.all(np.isfinite(got)) and got.min() == 0.0 and got[0, 0, 0] == 0.0 and got[1, 2, 1] == 0.0
    assert np.count_nonzero(got == 0.2) == table.size - 2


def test_ladder_sizes_never_exceed_the_configurations_directions():
    """Rungs floored at LADDER_MIN directions above the configuration's own are dropped (as for normals)."""
    assert synthesis.ladder_sizes(8000, 100) == []
    assert synthesis.ladder_sizes(8000, 300) == [(1000, 250), (2000, 250), (4000, 250)]


def test_lambertian_start_of_a_channel_the_lighting_never_reaches_is_zero():
    """A channel whose lighting-matrix rows are all 0 (``||L 1||^2 = 0``: a probe black in that channel) has
    no least-squares constant: 0, not NaN from 0 / 0; the other channels keep theirs."""
    L = np.random.default_rng(3).uniform(0.0, 1.0, (30, 9, 3))
    L[:, :, 2] = 0.0
    y = L.sum(axis=1) * np.array([0.3, 0.2, 0.1])
    with np.errstate(all="raise"):
        np.testing.assert_allclose(synthesis.lambertian_start(L, y), [0.3, 0.2, 0.0], rtol=1e-12, atol=0)


def test_first_adam_step_follows_the_hand_computed_smoothness_gradient():
    """Adam's first step moves each entry of ``log f`` by the learning rate against the sign of its gradient.
    With the smoothness weight so large that the image's term is negligible, that sign is the one of the
    gradient of sum((Delta_t log f)^2) + sum((Delta_s log f)^2) computed here by hand (an entry minus each of its
    up to four st neighbours, per channel): a term dropped, taken along the wrong axis or of the wrong sign
    moves some entries the wrong way."""
    probe, truth, shot = _sky_shot()
    rng = np.random.default_rng(16)
    g = np.log(truth) + rng.uniform(-1.0, 1.0, truth.shape)      # log f of the start, (4, 4, 3)
    grad = np.zeros_like(g)
    grad[1:] += 2.0 * (g[1:] - g[:-1])
    grad[:-1] -= 2.0 * (g[1:] - g[:-1])
    grad[:, 1:] += 2.0 * (g[:, 1:] - g[:, :-1])
    grad[:, :-1] -= 2.0 * (g[:, 1:] - g[:, :-1])
    assert np.abs(grad).min() > 0.2                               # every sign decided
    settings = synthesis.SynthesisSettings(spp=1, learning_rate=0.05, smoothness=1e5, seed=3)
    start = np.exp(g).astype(np.float32)
    run = synthesis.optimise_table(shot.image, shot.mask, probe, start, settings, budget_s=1e9, max_iterations=1)
    step = np.log(run["table"]) - np.log(start.astype(np.float64))
    np.testing.assert_allclose(step, -0.05 * np.sign(grad), rtol=1e-3)


def test_optimise_table_clock_budget_and_early_stop(monkeypatch):
    """A stand-in clock that advances 5 s per reading (two readings an iteration: 5 s an iteration) and 1000 s
    during each checkpoint: the clock counts the iterations only (5, 10, 15 s), the run stops at the first
    iteration that reaches the 12 s budget, and a checkpoint that answers True stops it at once."""
    import types

    probe, truth, shot = _sky_shot()
    now = [0.0]

    def perf_counter():
        now[0] += 5.0
        return now[0]

    monkeypatch.setattr(synthesis, "time", types.SimpleNamespace(perf_counter=perf_counter))
    settings = synthesis.SynthesisSettings(spp=1, seed=3)
    seen = []

    def checkpoint(it, clock, loss, table):
        seen.append((it, clock))
        now[0] += 1000.0                                          # a slow checkpoint: not on the clock
        return False

    run = synthesis.optimise_table(shot.image, shot.mask, probe, truth, settings, budget_s=12.0, max_iterations=6,
                                   eval_every=1, on_checkpoint=checkpoint)
    assert seen == [(1, 5.0), (2, 10.0), (3, 15.0)]
    assert run["iterations"] == 3 and run["time_s"] == 15.0 and len(run["losses"]) == 3
    stop = synthesis.optimise_table(shot.image, shot.mask, probe, truth, settings, budget_s=1e9, max_iterations=6,
                                    eval_every=1, on_checkpoint=lambda it, clock, loss, table: it == 2)
    assert stop["iterations"] == 2 and len(stop["losses"]) == 2


def test_optimise_table_loss_is_the_masked_relative_error_of_a_furnace():
    """Closed form: a Lambertian table rho / pi under a constant probe of radiance 1 renders rho on every fully
    covered pixel, so a start k x that table against an image of rho has loss (k - 1)^2 plus the render's own
    noise, whatever the mask. Here the mask is the left half of the sphere and every pixel outside it is NaN:
    a loss that counted unmasked pixels or was normalised by them would be far off."""
    from dataclasses import replace

    from mi_bivariate.geometry import SphereCamera

    _sky_shot()                                                   # the variant, as the tests above
    probe = Probe.constant(1.0, 8)
    rho = np.array([0.5, 0.3, 0.2])
    full = SphereCamera.create("orthographic", 16, radius_fraction=0.45).coverage_mask()
    mask = full & (np.arange(16)[None, :] < 8)
    image = np.where(mask[..., None], rho, np.nan).astype(np.float32)
    settings = synthesis.SynthesisSettings(spp=4, learning_rate=1e-9, smoothness=0.0, sampling="cosine", seed=3)
    losses = {}
    for k in (1.0, 2.0):
        start = np.broadcast_to(k * rho / np.pi, (4, 4, 3)).astype(np.float32)
        losses[k] = synthesis.optimise_table(image, mask, probe, start, settings, budget_s=1e9,
                                             max_iterations=2)["losses"]
    assert max(losses[1.0]) < 0.05                 # the render's own noise (0.016 measured on the whole sphere)
    assert all(0.95 < loss < 1.2 for loss in losses[2.0]), losses   # (2 - 1)^2 plus that noise
    # The plugin's sampling is the settings': the table's own importance sampling draws other directions.
    table = synthesis.optimise_table(image, mask, probe, np.broadcast_to(rho / np.pi, (4, 4, 3)).astype(np.float32),
                                     replace(settings, sampling="table"), budget_s=1e9, max_iterations=2)
    assert table["losses"] != losses[1.0] and max(table["losses"]) < 0.1



def test_speedup_and_time_to_the_linear_error_when_abs_improves_but_never_reaches_the_linear_route(monkeypatch):
    """Scripted errors and times (the start's relight error 0.5; AbS's checkpoints 0.4 at 1 s, 0.3 at 2 s; the
    linear route 0.2 in 0.5 s): AbS's best is 0.3 at 2 s and the linear route is at least as good, so the
    speedup is 2 s / 0.5 s = 4 (not its inverse), and AbS never reached the linear relight error (no time)."""
    scripted = {0.5: 0.5, 0.4: 0.4, 0.3: 0.3}               # a table's first node -> its relight error

    def relight_error(table_or_brdf, renderer, probe, probe_spec, truth, seed):
        table = table_or_brdf if isinstance(table_or_brdf, np.ndarray) else table_or_brdf.table
        return scripted.get(round(float(table[0, 0, 0]), 6), 0.2)   # the linear table (0.1) and the floor: 0.2

    def optimise_table(image, mask, probe, start, settings, budget_s=60.0, max_iterations=100000, eval_every=10,
                       on_checkpoint=None):
        tables = [np.full_like(np.asarray(start), value) for value in (0.4, 0.3)]
        if on_checkpoint is not None:
            for it, table in enumerate(tables, start=1):
                on_checkpoint(it, float(it), 0.5, table)
        return {"iterations": 2, "time_s": 2.0, "losses": [0.5, 0.5], "table": tables[-1]}

    def linear_run(shot, probe, config, n_normals, n_dirs, repeats, quiet=False, priors=(None, None)):
        rec = type("Rec", (), {"brdf": BivariateBRDF(np.full((8, 8, 3), 0.1)), "lighting_matrix": None,
                               "observations": type("Obs", (), {"values": None})()})()
        return rec, {"n_normals": n_normals, "n_dirs": n_dirs, "grid": [8, 8], "time_s": 0.5}

    class BRDFErrors:
        def __init__(self, truth):
            pass

        def __call__(self, brdf):
            return {"eq1": 0.1, "eq1_min": 0.1, "log": 0.1, "cosine": 0.1, "eq1_rgb": [0.1] * 3}

    monkeypatch.setattr(synthesis, "relight_error", relight_error)
    monkeypatch.setattr(synthesis, "render_noise", lambda *args: 0.0)
    monkeypatch.setattr(synthesis, "optimise_table", optimise_table)
    monkeypatch.setattr(synthesis, "linear_run", linear_run)
    monkeypatch.setattr(synthesis.metrics, "BRDFErrors", BRDFErrors)
    monkeypatch.setattr(synthesis, "lambertian_start", lambda L, values: np.full(3, 0.5))
    config = _tiny_abs_config(monkeypatch)
    r = synthesis.analysis_by_synthesis("ggx:diffuse=0.2,specular=0.5,alpha=0.2", "synthetic:1", config=config,
                                        linear_ladder=(), ladder_grid_fractions=(), ladder_repeats=1)
    assert [t["relight"] for t in r["trace"]] == [0.5, 0.4, 0.3] and r["linear"]["relight"] == 0.2
    assert r["abs"]["best_relight"] == 0.3 and r["abs"]["best_relight_time_s"] == 2.0
    assert r["speedup"] == pytest.approx(4.0) and r["ladder_speedup"] == pytest.approx(4.0)
    assert r["abs"]["reached_linear_relight"] is False and r["abs"]["time_to_linear_relight_s"] is None
