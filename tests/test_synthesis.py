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
