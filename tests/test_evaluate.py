"""Batch evaluation: quick mode end to end, resume after a kill, worker processes, Dask, baselines."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import independent_relight_floor, sums_in_fixed_order

from mi_bivariate import analytic, baselines, bivariate
from mi_bivariate import evaluate as ev
from mi_bivariate import figures as figures_mod
from mi_bivariate import metrics
from mi_bivariate.bivariate import BivariateBRDF
from mi_bivariate.cli import main

# Tiny protocol for the mechanics tests (one input probe, no baselines): seconds per material.
MATERIALS = ["lambertian:albedo=0.5,0.3,0.2", "ggx:diffuse=0.2,specular=0.5,alpha=0.2",
             "oren-nayar:albedo=0.6,sigma=0.3"]
TINY_ARGS = ["--input-probes", "synthetic:1", "--novel-probes", "synthetic:7", "--resolution", "32",
             "--spp", "8", "--novel-spp", "4", "--novel-resolution", "16", "--normals", "300", "--dirs", "1000",
             "--grid", "8", "8",
             "--baselines", "--no-figures", "--no-progress"]
TINY = ev.EvalConfig(input_probes=("synthetic:1",), novel_probes=("synthetic:7",), resolution=32, spp=8,
                     novel_spp=4, novel_resolution=16, n_normals=300, n_dirs=1000, grid=(8, 8), baselines=())


def _numbers(record: dict) -> dict:
    """A record without its timings (what must reproduce exactly)."""
    r = json.loads(json.dumps(record))
    r.pop("timings", None)
    r.pop("threads", None)
    for e in r["inputs"].values():
        e.pop("timings", None)
        for b in e.get("baselines", {}).values():
            b.pop("time_s", None)
    return r


def test_quick_end_to_end(tmp_path, capsys):
    out = tmp_path / "quick"
    assert main(["evaluate", "--quick", "--out", str(out), "--no-progress"]) == 0
    records = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert len(records) == 2
    for r in records:
        assert set(r["inputs"]) == set(ev.probe_label(p) for p in ev.EvalConfig.quick(
            shared_data=ev.have_shared_data()).input_probes)
        floor = r["floor"]
        for e in r["inputs"].values():
            for key in ("eq1", "eq1_min", "cosine", "log"):
                assert np.isfinite(e["recovered"][key]) and e["recovered"][key] >= 0
                assert np.isfinite(e["baselines"]["ggx"]["errors"][key])
            probe = next(iter(e["images"]))
            relight = e["images"][probe]
            assert 0 < relight["rel_rmse"] < 10
            if relight["floor"] >= max(metrics.MIN_RELIGHT_FLOOR, 2.0 * r["reference_noise"][probe]):
                assert relight["ratio"] == pytest.approx(relight["rel_rmse"] / relight["floor"])
            else:  # written as null: the floor is the references' noise
                assert relight["ratio"] is None
            assert e["adequacy"]["rank_fraction"] > 0
            # Where the image looks: observed cells, regions; floors under their own names.
            assert 0 < e["recovered"]["observed_fraction"] <= 1 and np.isfinite(e["recovered"]["eq1_observed"])
            assert set(e["recovered"]["regions"]) == set(metrics.REGION_NAMES)
            assert sum(v["share"] for v in e["recovered"]["regions"].values()) == pytest.approx(1.0)
            assert e["observed"]["nodes"] > 0
        assert r["floors"]["grid_floor"] == pytest.approx(floor["eq1"], rel=1e-9)
        assert 0 <= r["floors"]["exact_floor"] <= r["floors"]["grid_floor"] * 1.001
        assert r["relight_floor"] == {k: v["rel_rmse"] for k, v in r["floor_images"].items()}
        art = ev.load_artifacts(ev.artifact_path(out, r))
        assert art["floor"].shape == (12, 12, 3) and art["mask"].dtype == bool
        # The saved tables reproduce the recorded errors (figures are drawn from them).
        truth = ev.load_truth(ev.MaterialSpec(r["material"], r["kind"], r["spec"]))
        errors = metrics.BRDFErrors(truth)
        assert errors(BivariateBRDF(art["floor"]))["log"] == pytest.approx(floor["log"], rel=1e-6)
        # The exact phi_d average scored by the metrics is bivariate.reduction_error's exact floor, and
        # the recorded exact floor over the observed cells is it over the saved observed nodes.
        exact = bivariate.phi_d_average(truth)
        assert errors(exact)["eq1"] == pytest.approx(r["floors"]["exact_floor"], rel=1e-6)
        for label, e in r["inputs"].items():
            there = errors(exact, observed_nodes=art[f"observed_nodes__{label}"])["eq1_observed"]
            assert e["exact_floor_observed"] == pytest.approx(there, rel=1e-9)
            assert there > 0
            confident = e["confident"]
            assert confident["nodes"] == 0 or (np.isfinite(confident["exact_floor_eq1"])
                                               and confident["exact_floor_eq1"] > 0)
        probe = next(iter(r["inputs"]))
        assert errors(BivariateBRDF(art[f"recovered__{probe}"]))["eq1"] == pytest.approx(
            r["inputs"][probe]["recovered"]["eq1"], rel=1e-6)
    csv_lines = (out / "summary.csv").read_text().splitlines()
    assert len(csv_lines) == 1 + 2 * len(records)
    # The like-for-like floors reach the summary, one per input row, as recorded.
    rows = list(csv.DictReader(csv_lines))
    recorded = {(r["material"], label): e for r in records for label, e in r["inputs"].items()}
    for row in rows:
        e = recorded[(row["material"], row["input_probe"])]
        assert float(row["exact_floor_observed"]) == pytest.approx(e["exact_floor_observed"], rel=1e-5)
        if e["confident"]["nodes"]:
            assert float(row["exact_floor_confident"]) == pytest.approx(e["confident"]["exact_floor_eq1"], rel=1e-5)
    figures = sorted(p.name for p in (out / "figures").glob("*.png"))
    assert {"fig3_reduction.png", "fig5_validation.png", "fig6_errors.png", "fig6_incident.png",
            "fig7_environment.png", "tables.png", "baselines.png"} <= set(figures)
    summary = capsys.readouterr().out
    assert "materials" in summary
    # The summary says where the priors came from (--quick: packaged, which saw shared materials).
    sources = {e["prior"].split(":")[0].split(" (")[0] for r in records for e in r["inputs"].values()}
    assert "  priors: " in summary and all(f"{k} (" in summary for k in sources), summary
    # The Fig. 3 analogue draws the exact floor (the paper's curve), the grid floor beside it.
    fig = figures_mod.plot_reduction_ranking(records, {r["material"]: ev.load_artifacts(ev.artifact_path(out, r))
                                                       for r in records}, next(iter(records[0]["floor_images"])))
    curves = {line.get_label(): line.get_ydata() for line in fig.axes[0].get_lines()}
    order = sorted(records, key=lambda r: r["floors"]["exact_floor"])
    np.testing.assert_allclose(curves["exact floor (phi_d average): Eq. 1"],
                               [r["floors"]["exact_floor"] for r in order])
    np.testing.assert_allclose(curves["grid floor (12 x 12 table): Eq. 1 relative RMS"],
                               [r["floor"]["eq1"] for r in order])
    # The results page's tables come from one command over this folder.
    script = Path(__file__).resolve().parents[1] / "scripts" / "results_tables.py"
    page = subprocess.run([sys.executable, str(script), str(out)], capture_output=True, text=True, check=True).stdout
    assert "exact floor" in page and "relight" in page
    assert sum(line.startswith(f"| {records[0]['material']} |") for line in page.splitlines()) >= 2
    # Reference renders of truths and reductions are cached per material and probe.
    assert len(list((out / ev.REFERENCE_DIR).glob("*.npz"))) >= 2 * len(records)


def test_config_validation_and_noise_option():
    for bad in (dict(noise=-0.1), dict(noise=float("nan")), dict(renderer="raytrace"), dict(prior="/no/such.npz")):
        with pytest.raises(ev.InputError):
            ev.EvalConfig(**bad).validate()
    assert ev.EvalConfig(noise=0.02).hash() != ev.EvalConfig().hash()
    assert ev.EvalConfig().noise == 0.0 and ev.EvalConfig().renderer == "reference"    # clean by default


def test_config_refuses_what_no_run_can_use(tmp_path):
    """Novel renders under 4 pixels wide, reference direction counts that are not 3 non-negative numbers, an
    unknown baseline and an alpha out of range are refused before any work; the smallest allowed values pass. The
    library's front door refuses fewer than 1 job as the CLI does (it ran them in-process), making no folder."""
    for bad in (dict(novel_resolution=3), dict(reference_directions=(64, -1, 64)), dict(reference_directions=(64, 64)),
                dict(baselines=("ggx", "phong")), dict(alpha=-1.0)):
        with pytest.raises(ev.InputError):
            ev.EvalConfig(**bad).validate()
    ev.EvalConfig(novel_resolution=4, reference_directions=(0, 0, 1), baselines=(), noise=1.0).validate()
    for jobs in (0, -2):
        with pytest.raises(ev.InputError, match="--jobs"):
            ev.run_evaluation(["lambertian"], tmp_path / "eval", config=TINY, jobs=jobs, progress=False)
    assert not (tmp_path / "eval").exists()


def test_quick_keeps_the_settings_given():
    """``EvalConfig.quick`` (``evaluate --quick``) takes the small sizes and, without the shared data, synthetic
    probes, but a setting given with it wins (``--quick --seed 3``)."""
    cfg = ev.EvalConfig.quick(shared_data=False, seed=3, novel_resolution=16)
    assert (cfg.seed, cfg.novel_resolution, cfg.grid, cfg.resolution) == (3, 16, (12, 12), 48)
    assert cfg.input_probes == ("synthetic:1", "synthetic:3") and cfg.novel_probes == ("synthetic:7",)
    assert ev.EvalConfig.quick(novel_probes=("pisa_256",)).input_probes == ev.DEFAULT_INPUT_PROBES


def test_the_render_cache_keys_every_setting_of_a_render(tmp_path, monkeypatch):
    """A cached render of the truth is reused only for the same seed, resolution, render (``cache_key``), probe
    values under the probe's name and reference directions; each of them changed renders again (the stand-in
    renderer returns the seed, the resolution and the directions it was given)."""
    from types import SimpleNamespace

    from mi_bivariate import reference
    from mi_bivariate.evaluate.renders import Renderer
    from mi_bivariate.geometry import SphereGeometry
    from mi_bivariate.merl import MERLBRDF
    from mi_bivariate.probes import Probe
    from mi_bivariate.sources import MaterialSpec

    def stand_in(bsdf, probe, resolution, seed, directions):
        image = np.full((resolution, resolution, 3), seed + 1000.0 * sum(directions), np.float32)
        return SimpleNamespace(image=image, mask=np.ones((resolution, resolution), bool),
                               geometry=SphereGeometry(4.0, 4.0, 3.0, np.eye(4)))

    monkeypatch.setattr(reference, "render_reference", stand_in)
    truth = MERLBRDF(np.full((90, 90, 180, 3), 0.1, np.float32), name="grey")
    spec = MaterialSpec("grey", "analytic", "lambert")
    probes = {1.0: Probe.constant(1.0, 8), 2.0: Probe.constant(2.0, 8)}
    few, more = (ev.EvalConfig(reference_directions=d) for d in ((4, 8, 4), (4, 8, 5)))
    settings = [(few, 1.0, 8, 1, "truth"), (few, 1.0, 8, 2, "truth"), (few, 1.0, 12, 1, "truth"),
                (few, 1.0, 8, 1, "grid"), (few, 2.0, 8, 1, "truth"), (more, 1.0, 8, 1, "truth")]
    for cached in (0, 1):                                   # each rendered once, then read back
        renderers = {id(cfg): Renderer(cfg, spec, str(tmp_path), truth=truth) for cfg in (few, more)}
        for cfg, light, resolution, seed, key in settings:
            renderer = renderers[id(cfg)]
            before = (renderer.renders, renderer.cached)
            shot = renderer.render(None, probes[light], "constant", resolution, seed, 0, cache_key=key)
            done = (renderer.renders - before[0], renderer.cached - before[1])
            assert done == (1 - cached, cached), (cfg.reference_directions, light, resolution, seed, key)
            assert shot.image.shape == (resolution, resolution, 3)
            assert shot.image[0, 0, 0] == seed + 1000.0 * sum(cfg.reference_directions)
    assert len(list(tmp_path.glob("*.npz"))) == len(settings)


def test_the_views_of_a_noisy_input_get_independent_noise():
    """With ``--noise``, the views of an input ``"a+b"`` once got the same draws (one seed): their noises were
    perfectly correlated (0.99999), not the independent noise of two photos. Now each view has its own seed;
    the first view (and a single input) keeps the noise it had."""
    from mi_bivariate.evaluate import protocol
    from mi_bivariate.evaluate.renders import Shot
    from mi_bivariate.noise import add_camera_noise

    class Flat:  # a lit square per view, 1 and 3 units
        def render(self, bsdf, probe, part, resolution, seed, spp, cache_key=None):
            image = np.zeros((resolution, resolution, 3), np.float32)
            image[4:-4, 4:-4] = 1.0 if part == "a" else 3.0
            return Shot(image, image[..., 0] > 0, None)

    cfg = ev.EvalConfig(resolution=32, noise=0.05, seed=5)
    (a, b), _ = protocol.render_inputs(Flat(), cfg, "a+b", [None, None], None)
    corr = np.corrcoef((a[4:-4, 4:-4] - 1.0).ravel(), (b[4:-4, 4:-4] - 3.0).ravel())[0, 1]
    assert abs(corr) < 0.1, corr
    (single,), _ = protocol.render_inputs(Flat(), cfg, "a", [None], None)
    np.testing.assert_array_equal(a, single)
    np.testing.assert_array_equal(single, add_camera_noise(Flat().render(None, None, "a", 32, 5, 0).image, 0.05,
                                                           seed=5 + ev.NOISE_SEED_OFFSET))


@pytest.fixture(scope="module")
def resumed(tmp_path_factory):
    """Kill a CLI run after its first material, cut its last line, resume in-process."""
    out = tmp_path_factory.mktemp("resume")
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "mi_bivariate.cli", "evaluate", *MATERIALS, "--out", str(out), *TINY_ARGS]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    results = out / "results.jsonl"
    deadline = time.monotonic() + 90
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            if results.is_file() and results.read_text().count("\n") >= 1:
                break
            time.sleep(0.05)
    finally:
        proc.kill()                                       # SIGKILL mid-run: no cleanup at all
        proc.wait()
    first = results.read_text().splitlines()
    finished = [json.loads(line)["material"] for line in first]
    stamps = {m: ev.artifact_path(out, ev.MaterialSpec(m, "", "").slug, TINY.hash()).stat().st_mtime_ns
              for m in finished}
    with open(results, "a") as f:                         # a last line cut mid-write
        f.write('{"material": "cut-off", "config_ha')
    new = []
    records = ev.run_evaluation(MATERIALS, out, config=TINY, progress=False, figures=False,
                                on_record=lambda r: new.append(r["material"]))
    return {"out": out, "first": first, "finished": finished, "stamps": stamps, "new": new, "records": records}


def test_resume_after_kill_and_truncation(resumed):
    out, first, finished, records = resumed["out"], resumed["first"], resumed["finished"], resumed["records"]
    assert 1 <= len(first) < len(MATERIALS), "the run must be interrupted after its first material"
    assert sorted(resumed["new"]) == sorted(set(r["material"] for r in records) - set(finished))  # none redone
    assert len(records) == len(MATERIALS)                                                         # none lost
    lines = (out / "results.jsonl").read_text().splitlines()
    assert lines[:len(first)] == first                                      # finished ones kept verbatim
    assert all(json.loads(line) for line in lines) and len(lines) == len(MATERIALS)
    for m, stamp in resumed["stamps"].items():
        assert ev.artifact_path(out, ev.MaterialSpec(m, "", "").slug, TINY.hash()).stat().st_mtime_ns == stamp
    # A rerun with everything done computes nothing; another config has another hash.
    again = []
    ev.run_evaluation(MATERIALS, out, config=TINY, progress=False, figures=False, on_record=again.append)
    assert again == []
    assert ev.EvalConfig(**{**TINY.to_dict(), "seed": 1, "grid": (8, 8)}).hash() != TINY.hash()


def _close(a, b, rtol: float, atol: float = 0.0, path: str = "", psnr_atol: float = 0.0) -> bool:
    """Recursive comparison; PSNR values (dB) get ``psnr_atol`` besides ``rtol``."""
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_close(a[k], b[k], rtol, atol, f"{path}/{k}", psnr_atol) for k in a)
    if isinstance(a, list):
        return len(a) == len(b) and all(_close(x, y, rtol, atol, path, psnr_atol) for x, y in zip(a, b))
    if isinstance(a, float):
        tol = rtol * max(abs(a), abs(b)) + (psnr_atol if path.endswith("/psnr") else atol)
        ok = a == b or abs(a - b) <= tol
        if not ok:
            print(f"differs at {path}: {a!r} vs {b!r}")
        return ok
    return a == b


def _without_rounding_ratios(record: dict) -> dict:
    """Drop relight ratios whose floor is float rounding (the Lambertian's exact reduction renders
    like its truth to ~1e-7): rounding / rounding depends on the summation order."""
    r = json.loads(json.dumps(record))
    for e in r["inputs"].values():
        for v in e["images"].values():
            if v.get("floor", 1.0) < 1e-5:
                v.pop("ratio", None)
    return r


def test_jobs_and_dask_reproduce_in_process(resumed, tmp_path):
    # Worker processes (spawn, 1 Dr.Jit thread each) and in-process with 1 thread: identical numbers.
    pooled = ev.run_evaluation(MATERIALS[:2], tmp_path / "pooled", config=TINY, jobs=2, progress=False,
                               figures=False)
    assert all(r["threads"] == ev.threads_per_job(2) for r in pooled)
    serial = ev.run_evaluation(MATERIALS[:2], tmp_path / "serial", config=TINY, threads=pooled[0]["threads"],
                               progress=False, figures=False)
    # Identical up to float64 rounding: numpy's SIMD sums depend on memory alignment, which differs
    # between a fresh worker and a long-lived process (seen on Eq. 1 values of ~1e-17, exact reductions).
    assert _close([_numbers(r) for r in serial], [_numbers(r) for r in pooled], rtol=1e-12, atol=1e-15)
    # Dask (in-process worker) and the resumed run with every core's threads: on the CPU the lighting
    # matrix sums in one order for any thread count, so the same up to float64 rounding again; under
    # CUDA's atomics, up to the float32 summation order of the lighting matrix.
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=1, processes=False, threads_per_worker=1,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        dasked = ev.run_evaluation(MATERIALS[:1], tmp_path / "dask", config=TINY, dask=client, progress=False,
                                   figures=False)
    resumed_by = {r["material"]: r for r in resumed["records"]}
    for r in dasked + serial:
        other = resumed_by[r["material"]]
        if sums_in_fixed_order():
            assert _close(_numbers(r), _numbers(other), rtol=1e-12, atol=1e-15)
            continue
        # Under CUDA image errors are compared absolutely at 1e-5: float32 rounding of L (its
        # summation order varies) moves a relight error of ~4e-3 by ~2e-6 through the two-stage
        # solve (noise estimate, basis prior).
        # A PSNR is 20 log10 of the same error: an absolute 1e-5 on a relight error of ~4e-3 is
        # 20 / ln 10 * 1e-5 / 4e-3 = 0.02 dB (measured: 56.355 vs 56.363 dB).
        assert _close(_without_rounding_ratios(_numbers(r)), _without_rounding_ratios(_numbers(other)),
                      rtol=1e-4, atol=1e-5, psnr_atol=0.03)


def test_baseline_fit_recovers_its_own_model():
    # Data made by the model itself through a random lighting matrix: the fit must find it.
    truth = analytic.CookTorranceGGX([0.3, 0.2, 0.1], [0.05, 0.06, 0.07], alpha=0.15, ior=1.7)
    averager = baselines.PhiAverager(12, 12)
    rng = np.random.default_rng(0)
    L = (rng.random((1500, 144, 3)) * (rng.random((1500, 144, 1)) < 0.1)).astype(np.float32)
    I = np.einsum("mnc,nc->mc", L, averager.average(truth).reshape(-1, 3))
    fit = baselines.fit_baseline("ggx", L, I, grid=(12, 12), averager=averager)
    assert fit.relative_residual < 1e-3
    assert fit.params["alpha"] == pytest.approx(0.15, rel=0.02)
    assert np.asarray(fit.params["kd"]) == pytest.approx([0.3, 0.2, 0.1], rel=0.05)


def test_phi_averager_matches_reduce():
    from mi_bivariate.bivariate import BivariateBRDF

    model = baselines.WardIsotropic([0.2, 0.1, 0.1], 0.3, alpha=0.2)
    table = baselines.PhiAverager(10, 12, n_phi=30).average(model)
    np.testing.assert_allclose(table, BivariateBRDF.reduce(model, n_t=10, n_s=12, n_phi=30).table, rtol=1e-5)


def test_bad_material_is_one_line_error(tmp_path, capsys):
    assert main(["evaluate", "no-such-material", "--out", str(tmp_path), *TINY_ARGS]) == 2
    err = capsys.readouterr().err
    assert err.startswith("mi-bivariate: error: no-such-material") and len(err.strip().splitlines()) == 1


def test_evaluate_abs_records_both_routes_scored_by_the_converged_renderer(tmp_path, capsys):
    """``evaluate --abs``: the analysis-by-synthesis record has every linear point timed alike (the
    config's sizes and the ladder's, 3 runs each), the relight floor (recomputed here from the exact
    reduction, rendered as the evaluation renders it), the scoring renders' own noise, and the
    fastest linear run reaching AbS's best."""
    import dataclasses

    from mi_bivariate import synthesis

    material = MATERIALS[1]                              # GGX: not exactly bivariate, the floor is > 0
    out = tmp_path / "abs"
    assert main(["evaluate", material, "--out", str(out), *TINY_ARGS, "--abs", "1", "--abs-time-factor", "2"]) == 0
    assert "analysis by synthesis" in capsys.readouterr().out
    (r,) = [json.loads(line) for line in (out / "analysis_by_synthesis.jsonl").read_text().splitlines()]
    config = dataclasses.replace(TINY, novel_resolution=16)
    assert r["scoring"]["renderer"] == "reference" and r["scoring"]["resolution"] == 16
    assert r["novel_probe"] == ev.probe_label(config.novel_probes[0])

    seed = config.seed + 1                               # the evaluation's seed for its first novel probe
    want = independent_relight_floor(config, material, config.novel_probes[0], seed, 16)
    assert want > 1e-3 and r["relight_floor"] == pytest.approx(want, rel=1e-6)

    assert set(r["relight_noise"]) == {"truth", "linear_table", "abs_best_table"}
    assert all(0 < v < 5e-3 for v in r["relight_noise"].values()), r["relight_noise"]
    points = r["linear_ladder"] + [r["linear"]]
    assert ([(p["n_normals"], p["n_dirs"], tuple(p["grid"])) for p in points]
            == [*synthesis.ladder_rungs(300, 1000, (8, 8)), (300, 1000, (8, 8))])
    for p in points:
        assert len(p["times_s"]) == 3 and p["time_s"] == sorted(p["times_s"])[1] and np.isfinite(p["relight"])
        # Each run's total is its stages' sum; the stages are per-stage medians (no timing tolerance:
        # the sum of medians and the median of sums part on a loaded machine).
        assert p["times_s"] == pytest.approx([sum(run.values()) for run in p["stage_runs"]], rel=1e-12)
        assert p["stages"] == {k: float(np.median([run[k] for run in p["stage_runs"]])) for k in p["stages"]}
        assert set(p["stages"]) == set(synthesis.LINEAR_STAGES) and all(v > 0 for run in p["stage_runs"] for v in run.values())
    fastest, speedup = synthesis.linear_reaches(points, r["abs"]["best_relight"], r["abs"]["best_relight_time_s"])
    key = ("n_normals", "n_dirs", "time_s", "relight")    # the default point's record also has its BRDF errors
    got = r["linear_to_abs_best"]
    assert (got is None) == (fastest is None) and r["ladder_speedup"] == speedup
    if fastest is not None:
        assert {k: got[k] for k in key} == {k: fastest[k] for k in key}

    # A rerun resumes: the material is reported from its record, not run and appended again; another
    # time factor is another run.
    assert main(["evaluate", material, "--out", str(out), *TINY_ARGS, "--abs", "1", "--abs-time-factor", "2"]) == 0
    assert "an earlier run" in capsys.readouterr().out
    assert len((out / "analysis_by_synthesis.jsonl").read_text().splitlines()) == 1
    assert main(["evaluate", material, "--out", str(out), *TINY_ARGS, "--abs", "1", "--abs-time-factor", "1"]) == 0
    lines = [json.loads(line) for line in (out / "analysis_by_synthesis.jsonl").read_text().splitlines()]
    assert [r["time_factor"] for r in lines] == [2.0, 1.0]


def test_cached_renders_are_keyed_by_the_truths_values(tmp_path):
    """A render cached for one truth table is not reused for another under the same material name
    (as when the decoder of the neural truths changed), and is reused for the same values."""
    from mi_bivariate.evaluate.renders import Renderer
    from mi_bivariate.merl import MERLBRDF
    from mi_bivariate.probes import Probe
    from mi_bivariate.sources import MaterialSpec
    from mi_bivariate.variants import ensure_variant

    ensure_variant()
    config = ev.EvalConfig.quick(shared_data=False)
    spec, probe = MaterialSpec("grey", "analytic", "lambert"), Probe.constant(1.0, 16)
    table = np.full((90, 90, 180, 3), 0.1, np.float32)
    runs = []
    for values in (table, np.nextafter(table, np.float32(1)), table.copy()):  # the second: one float32 ulp more
        truth = MERLBRDF(values, name="grey")
        renderer = Renderer(config, spec, str(tmp_path), truth=truth)
        shot = renderer.render(BivariateBRDF(np.full((6, 6, 3), 0.1, np.float32)), probe, "constant", 16, 1,
                               config.novel_spp, cache_key="truth")
        runs.append((renderer.renders, renderer.cached, shot.image))
    assert [r[:2] for r in runs] == [(1, 0), (1, 0), (0, 1)]
    np.testing.assert_array_equal(runs[2][2], runs[0][2])
    assert len(list(tmp_path.glob("*.npz"))) == 2
    # A MERL file's truth is keyed by its values alone: the same file touched (a new time stamp) hits
    # the cache; without the truth, its size and time stand in for the values.
    merl = tmp_path / "grey.binary"
    merl.write_bytes(b"stand-in")
    counts = []
    for stamp in (1_000_000_000, 2_000_000_000, 2_000_000_000):
        os.utime(merl, ns=(stamp, stamp))
        for truth in (MERLBRDF(table, name="grey"), None):
            renderer = Renderer(config, MaterialSpec("grey", "merl", str(merl)), str(tmp_path / "merl"), truth=truth)
            renderer.render(BivariateBRDF(np.full((6, 6, 3), 0.1, np.float32)), probe, "constant", 16, 1,
                            config.novel_spp, cache_key="truth")
            counts.append((renderer.renders, renderer.cached))
    assert counts == [(1, 0), (1, 0), (0, 1), (1, 0), (0, 1), (0, 1)]


def test_a_prior_file_brings_its_own_basis_prior_or_none(tmp_path):
    """``evaluate --prior FILE`` loads the priors as ``recover --prior FILE`` does: the basis prior
    ``learn-prior`` wrote beside it, or none; never the packaged basis, which saw every shared material."""
    import shutil

    from mi_bivariate import basis_prior as bp
    from mi_bivariate import prior as pr
    from mi_bivariate.evaluate.protocol import MaterialTask, choose_priors
    from mi_bivariate.sources import MaterialSpec

    prior_file, basis_file = tmp_path / "mine.npz", tmp_path / "mine_basis.npz"
    shutil.copyfile(pr.DEFAULT_PRIOR_PATH, prior_file)
    cfg = ev.EvalConfig(prior=str(prior_file))
    task = MaterialTask(MaterialSpec("brass", "nbrdf", "brass"), cfg)
    smooth, basis, said = choose_priors(task)
    assert isinstance(smooth, pr.Prior) and basis is None and "no basis prior" in said
    without = cfg.hash()

    shutil.copyfile(bp.DEFAULT_BASIS_PRIOR_PATH, basis_file)
    smooth, basis, said = choose_priors(task)
    assert isinstance(basis, bp.BasisPrior) and str(basis_file) in said
    assert cfg.hash() != without  # results with and without the basis file never mix


def test_a_merl_file_changed_or_another_file_of_its_name_is_evaluated_again(tmp_path):
    """Resuming keeps a MERL file's record only for the same bytes: the label (the file's stem) alone would
    report the old material's numbers for a new one. The same bytes by another path are not evaluated
    again, and each version's artifacts have a name of their own."""
    import shutil

    first, other, copy = tmp_path / "a" / "x.binary", tmp_path / "b" / "x.binary", tmp_path / "c" / "x.binary"
    for path in (first, other, copy):
        path.parent.mkdir()
    analytic.to_merl(analytic.Lambertian(0.5)).write(first)
    analytic.to_merl(analytic.Lambertian(0.1)).write(other)
    shutil.copyfile(first, copy)
    out = tmp_path / "eval"

    def evaluate(spec):
        seen = []
        ev.run_evaluation([str(spec)], out, config=TINY, progress=False, figures=False, on_record=seen.append)
        records = ev.read_records(out / ev.RESULTS_FILE, TINY.hash())
        assert [r["material"] for r in records] == ["x"]  # one record per material, the latest
        assert ev.artifact_path(out, records[0]).is_file()
        return len(seen), records[0]

    runs, a = evaluate(first)
    assert runs == 1 and a["spec"] == str(first) and len(a["source_sha256"]) == 16
    assert evaluate(first) == (0, a)                # the same file: resumed, nothing evaluated
    assert evaluate(copy) == (0, a)                 # the same bytes by another path: resumed too
    runs, b = evaluate(other)                       # another file of the same name
    assert runs == 1 and b["spec"] == str(other) and b["source_sha256"] != a["source_sha256"]
    assert b["slug"] != a["slug"] and ev.artifact_path(out, a).is_file()  # the first one's artifacts kept
    analytic.to_merl(analytic.Lambertian(0.9)).write(other)     # the same file, new bytes
    assert evaluate(other)[0] == 1


def test_evaluate_abs_resumes_only_for_the_same_bytes(tmp_path, monkeypatch, capsys):
    """``evaluate --abs`` reports a material from its earlier record only when that record came from the same
    bytes (the digests its evaluation record keeps, by the evaluation's own rule ev.same_data): a file rewritten
    under the same name is run again, and the first bytes again find their own record, not the latest one.
    The evaluation and analysis by synthesis are stand-ins: only the resume rule is under test."""
    from mi_bivariate import synthesis

    calls, digest = [], {}

    def evaluation(materials, out, config=None, **kwargs):
        Path(out).mkdir(exist_ok=True)
        return [{"material": "x", "spec": materials[0], **digest}]

    def stand_in(spec, input_probe, config=None, data_dir=None, time_factor=1.0):
        calls.append(spec)
        return {"material": "x", "input_probe": ev.probe_label(input_probe), "config_hash": config.hash(),
                "linear": {"eq1": 1.0, "relight": 1.0, "time_s": 1.0}, "relight_floor": 1.0,
                "abs": {"final": {"eq1": 1.0}, "best_relight": 1.0, "best_relight_time_s": 1.0, "time_s": 1.0,
                        "iterations": 1, "reached_linear_relight": False},
                "linear_to_abs_best": None, "ladder_speedup": None}

    monkeypatch.setattr(ev, "run_evaluation", evaluation)
    monkeypatch.setattr(ev, "format_summary", lambda records: "")
    monkeypatch.setattr(synthesis, "analysis_by_synthesis", stand_in)
    merl_file, out = tmp_path / "x.binary", tmp_path / "abs"
    analytic.to_merl(analytic.Lambertian(0.5)).write(merl_file)

    def run(**digests):
        digest.clear()
        digest.update(digests)
        assert main(["evaluate", str(merl_file), "--out", str(out), *TINY_ARGS, "--abs", "1"]) == 0
        capsys.readouterr()
        return [json.loads(line) for line in (out / "analysis_by_synthesis.jsonl").read_text().splitlines()]

    a, b, c, d = ("a" * 16, "b" * 16, "c" * 16, "d" * 16)
    assert len(run(source_sha256=a, shared_data_sha256=c)) == 1 and len(calls) == 1
    again = run(source_sha256=a, shared_data_sha256=c)                     # the same bytes: resumed
    assert len(again) == 1 and len(calls) == 1
    assert (again[0]["source_sha256"], again[0]["shared_data_sha256"]) == (a, c)
    assert len(run(source_sha256=b, shared_data_sha256=c)) == 2 and len(calls) == 2  # another file: run again
    assert len(run(source_sha256=a, shared_data_sha256=c)) == 2 and len(calls) == 2  # the first: its own record
    assert len(run(source_sha256=a, shared_data_sha256=d)) == 3 and len(calls) == 3  # another data folder
    assert len(run(source_sha256=a, shared_data_sha256=d)) == 3 and len(calls) == 3
    # Records written before the digests were kept, by the evaluation's own rule (ev.same_data): one without
    # the shared data's digest is reused; one without a MERL file's is run again.
    out.joinpath("analysis_by_synthesis.jsonl").unlink()
    assert len(run(source_sha256=a)) == 1 and len(run(source_sha256=a, shared_data_sha256=c)) == 1
    assert len(calls) == 4
    out.joinpath("analysis_by_synthesis.jsonl").unlink()
    assert len(run()) == 1 and len(run(source_sha256=a)) == 2 and len(calls) == 6


def test_warnings_are_named_recorded_and_said_by_the_process_writing_the_records(tmp_path):
    """A recovery's warnings ("image: ...") name the material and the input probe, go into the record once,
    and are said by run_evaluation's process (from a worker they printed in Python's two-line form)."""
    from mi_bivariate.errors import InputWarning
    from mi_bivariate.evaluate.protocol import _named

    assert _named("image: only 9 usable observations", "brass", ["grace_latlong_1k"]) == \
        "brass under grace_latlong_1k: only 9 usable observations"
    assert _named("image 1: dark", "brass", ["grace_latlong_1k", "uffizi_256"]) == "brass under uffizi_256: dark"
    assert _named("inadequate illumination", "brass", ["a", "b"]) == "brass under a+b: inadequate illumination"
    with pytest.warns(InputWarning) as said:
        (record,) = ev.run_evaluation([MATERIALS[0]], tmp_path / "e", config=TINY, progress=False, figures=False)
    label = record["material"]
    assert record["warnings"] and all(m.startswith(f"{label} under synthetic:1: ") for m in record["warnings"])
    assert len(set(record["warnings"])) == len(record["warnings"])
    assert [str(w.message) for w in said if str(w.message) in record["warnings"]] == record["warnings"]
    # Other warnings (numpy's) are said again once per place, not as often as they were recorded.
    import warnings

    from mi_bivariate.evaluate.protocol import _say_others

    repeat = warnings.WarningMessage(RuntimeWarning("overflow"), RuntimeWarning, "somewhere.py", 7)
    with warnings.catch_warnings(record=True) as again:
        warnings.simplefilter("default")
        _say_others([repeat] * 3)
    assert [str(w.message) for w in again] == ["overflow"]


def test_a_prior_file_that_saw_the_material_is_said(tmp_path):
    """``evaluate --prior FILE`` on a material the file's priors learnt from: the scores are not leave-one-out,
    and the evaluation says so."""
    import shutil

    from mi_bivariate import basis_prior as bp
    from mi_bivariate import prior as pr
    from mi_bivariate.errors import InputWarning
    from mi_bivariate.evaluate.protocol import MaterialTask, choose_priors
    from mi_bivariate.sources import MaterialSpec

    prior_file = tmp_path / "all.npz"
    shutil.copyfile(pr.DEFAULT_PRIOR_PATH, prior_file)               # the packaged priors saw every shared one
    shutil.copyfile(bp.DEFAULT_BASIS_PRIOR_PATH, tmp_path / "all_basis.npz")
    seen = pr.Prior.load(prior_file).provenance["materials"]
    task = MaterialTask(MaterialSpec(seen[0], "nbrdf", seen[0]), ev.EvalConfig(prior=str(prior_file)))
    with pytest.warns(InputWarning, match=f"{seen[0]}: .*all.npz and .*all_basis.npz learnt from this material"):
        choose_priors(task)
    # ... and a MERL file named as one of them (its path never matched the provenance's names before)
    named = MaterialTask(MaterialSpec(seen[0], "merl", str(tmp_path / f"{seen[0]}.binary")),
                         ev.EvalConfig(prior=str(prior_file)))
    with pytest.warns(InputWarning, match=f"learnt from a shared material named '{seen[0]}' \\(if this file"):
        choose_priors(named)
    other = MaterialTask(MaterialSpec("lambertian", "analytic", "lambertian"), ev.EvalConfig(prior=str(prior_file)))
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", InputWarning)
        choose_priors(other)


def test_a_merl_file_named_as_a_shared_material_is_said_to_be_seen_by_the_packaged_priors(tmp_path):
    """A MERL file ``brass.binary`` is scored with the packaged priors, which learnt from the shared 'brass':
    if it is that material, the score is not leave-one-out. The evaluation now says so (it said nothing);
    a file of another name is scored without a word."""
    import warnings

    from mi_bivariate import prior as pr
    from mi_bivariate.errors import InputWarning
    from mi_bivariate.evaluate.protocol import MaterialTask, choose_priors
    from mi_bivariate.sources import MaterialSpec

    seen = pr.default_prior().provenance["materials"][0]
    task = MaterialTask(MaterialSpec(seen, "merl", str(tmp_path / f"{seen}.binary")), ev.EvalConfig())
    with pytest.warns(InputWarning, match=f"learnt from a shared material named '{seen}'.*not leave-one-out"):
        assert choose_priors(task)[2].startswith("packaged")
    other = MaterialTask(MaterialSpec("mine", "merl", str(tmp_path / "mine.binary")), ev.EvalConfig())
    with warnings.catch_warnings():
        warnings.simplefilter("error", InputWarning)
        choose_priors(other)


def test_quick_says_a_shared_material_is_scored_by_priors_that_saw_it(tmp_path):
    """``--quick`` (``leave_one_out=False``) scores a shared MERL-NBRDF material with the packaged priors,
    which learnt from it: the evaluation says so per material, as for a MERL file of a shared name (it
    said nothing); with leave-one-out priors, or for a material they did not see, nothing is said."""
    import warnings

    from mi_bivariate import prior as pr
    from mi_bivariate.errors import InputWarning
    from mi_bivariate.evaluate.protocol import MaterialTask, choose_priors
    from mi_bivariate.sources import MaterialSpec

    seen = pr.default_prior().provenance["materials"][0]
    quick = ev.EvalConfig.quick(shared_data=True)
    assert not quick.leave_one_out
    with pytest.warns(InputWarning, match=f"{seen}: the packaged priors were learnt from this material.*not leave"):
        assert choose_priors(MaterialTask(MaterialSpec(seen, "nbrdf", seen), quick))[2].startswith("packaged")
    with warnings.catch_warnings():
        warnings.simplefilter("error", InputWarning)
        choose_priors(MaterialTask(MaterialSpec("not-shared", "nbrdf", "not-shared"), quick))
        choose_priors(MaterialTask(MaterialSpec("ggx:alpha=0.2", "analytic", "ggx:alpha=0.2"), quick))
