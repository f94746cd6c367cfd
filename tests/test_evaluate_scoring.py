"""The evaluation's scoring against independent truths: each recorded number recomputed by a second route
(hand-made inputs with known answers, numpy written out here, the reference renderer called directly), so
that a wrong floor, a swapped axis, a wrong seed or a median for a mean in the protocol fails a test."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from mi_bivariate import adequacy, analytic, metrics, prior, training_set
from mi_bivariate import evaluate as ev
from mi_bivariate.bivariate import BivariateBRDF
from mi_bivariate.evaluate import protocol
from mi_bivariate.merl import node_angles


def _eq1_by_hand(table: np.ndarray, f_bar: np.ndarray, min_value: float = 0.0) -> float:
    """Eq. 1 written out: ``sqrt(mean ((f - f_bar) / f)^2)`` over the nodes (theta_h, theta_d, phi_d, channel)
    with both directions above the horizon (finite in the 3D table) and f above ``min_value``."""
    f = np.asarray(table, np.float64)
    keep = np.isfinite(f).all(axis=-1, keepdims=True) & (f > min_value)
    rel = (f - f_bar[:, :, None, :]) / np.where(keep, f, 1.0)
    return float(np.sqrt(np.mean(rel[np.broadcast_to(keep, f.shape)] ** 2)))


def test_the_truth_and_its_floors_on_a_non_square_grid():
    """``load_truth_and_floor`` on a 6 x 9 grid (theta_h nodes x theta_d nodes): the exact phi_d average is
    numpy's nanmean over the valid phi_d, the exact floor and the grid floor are Eq. 1 written out here (all
    cells and f > 1e-3), of that average and of the 6 x 9 table read back at the MERL nodes. The diffuse part is
    weak: 14% of the values lie between 1e-4 and 1e-3 1/sr, so the f > 1e-3 numbers differ from the others."""
    material = ev.MaterialSpec("ggx", "analytic", "ggx:diffuse=0.002,0.001,0.0005,specular=0.5,alpha=0.15")
    task = protocol.MaterialTask(material, ev.EvalConfig(grid=(6, 9)))
    truth = protocol.load_truth_and_floor(task, {})
    table = np.asarray(truth.brdf.table, np.float64)
    f_bar = np.nanmean(table, axis=2)                       # below-horizon samples are NaN in a MERL table
    np.testing.assert_allclose(truth.exact, f_bar, rtol=1e-12)
    assert truth.floor.table.shape == (6, 9, 3)
    theta_h, theta_d, _ = node_angles()
    on_nodes = truth.floor.eval(theta_h[:, None], theta_d[None, :])
    floors = truth.floor_values
    assert floors["grid"] == [6, 9]
    assert floors["exact_floor"] == pytest.approx(_eq1_by_hand(table, f_bar), rel=1e-9)
    assert floors["exact_floor_min"] == pytest.approx(_eq1_by_hand(table, f_bar, 1e-3), rel=1e-9)
    assert floors["grid_floor"] == pytest.approx(_eq1_by_hand(table, on_nodes), rel=1e-9)
    assert floors["grid_floor_min"] == pytest.approx(_eq1_by_hand(table, on_nodes, 1e-3), rel=1e-9)
    assert floors["exact_floor"] < floors["grid_floor"]     # the grid's own cost comes on top
    assert floors["grid_floor_min"] != pytest.approx(floors["grid_floor"], rel=1e-3)
    assert truth.floor_errors["eq1"] == pytest.approx(floors["grid_floor"], rel=1e-9)
    assert truth.floor_errors["eq1_min"] == pytest.approx(floors["grid_floor_min"], rel=1e-9)


def test_a_recovery_is_scored_over_the_observed_and_the_confident_nodes():
    """``score_recovery`` with a lighting matrix whose observed nodes are known by hand (one-hot rows: a node
    seen by k rows has k effective rows and k pixels of signal, so it is observed from k = 8) and a per-node
    confidence whose smallest channel decides: each recorded error is the metric over those nodes."""
    n_t, n_s = 6, 9
    rng = np.random.default_rng(3)
    observed = rng.random((n_t, n_s)) < 0.6
    observed[:2] = True                                      # the specular rows seen, the mask not symmetric
    rows = []
    for j, seen in enumerate(observed.ravel()):
        one_hot = np.zeros((n_t * n_s, 3), np.float32)
        one_hot[j] = 1.0
        rows += [one_hot] * (10 if seen else 3)              # 3 rows: signal 3, but only 3 effective rows
    measured = rng.uniform(0.6, 1.0, (n_t, n_s, 3))
    doubtful = rng.random((n_t, n_s)) < 0.4
    measured[doubtful, 1] = 0.3                              # one channel under 0.5: not confident
    confident = ~doubtful

    truth_brdf = analytic.to_merl(analytic.CookTorranceGGX([0.2, 0.1, 0.05], 0.5, alpha=0.15))
    floor = BivariateBRDF.reduce(truth_brdf, n_t=n_t, n_s=n_s)
    exact = np.nanmean(np.asarray(truth_brdf.table, np.float64), axis=2)
    errors = metrics.BRDFErrors(truth_brdf)
    truth = protocol._Truth(truth_brdf, floor, exact, errors, errors(floor), {})
    recovered = BivariateBRDF(floor.table * rng.uniform(0.7, 1.3, floor.table.shape))
    rec = SimpleNamespace(lighting_matrix=np.stack(rows), brdf=recovered, solution=SimpleNamespace(measured=measured))

    entry, nodes = protocol.score_recovery(rec, truth, (n_t, n_s))
    np.testing.assert_array_equal(nodes, observed)
    assert entry["observed"]["nodes"] == int(observed.sum())
    assert entry["recovered"] == errors(recovered, observed_nodes=observed)
    assert entry["grid_floor_observed"] == errors(floor, observed_nodes=observed)["eq1_observed"]
    assert entry["exact_floor_observed"] == errors(exact, observed_nodes=observed)["eq1_observed"]
    assert entry["exact_floor_observed"] < entry["grid_floor_observed"]
    got = entry["confident"]
    assert got["nodes"] == int(confident.sum()) and got["node_fraction"] == pytest.approx(confident.mean())
    assert got["eq1"] == errors(recovered, observed_nodes=confident)["eq1_observed"]
    assert got["floor_eq1"] == errors(floor, observed_nodes=confident)["eq1_observed"]
    assert got["exact_floor_eq1"] == errors(exact, observed_nodes=confident)["eq1_observed"]
    assert len({got["eq1"], got["floor_eq1"], got["exact_floor_eq1"], entry["grid_floor_observed"]}) == 4


def test_a_node_seen_by_many_rows_with_little_signal_is_not_observed():
    """The observed-node rule needs both criteria: 8 effective rows *and* half a pixel's worth of signal. Node
    (0, 0) takes most of 60 rows; 20 of them give a share q of their value to node (0, 1) (q = 0.02), 20 to (0, 2)
    (q = 0.03), 20 to (1, 0) (q = 0.05): each has 20 effective rows and a signal of 20 q (0.4, 0.6, 1.0), so
    (0, 1) alone is not observed. Node (1, 1) is all of one row (signal 1, but one effective row) and (1, 2) is
    in none: neither is observed. The recorded node count and the nodes given to the metric follow that rule."""
    n_t, n_s = 2, 3
    rows = []
    for node, q in ((1, 0.02), (2, 0.03), (3, 0.05)):
        row = np.zeros((n_t * n_s, 3))
        row[0], row[node] = 1.0 - q, q
        rows += [row] * 20
    alone = np.zeros((n_t * n_s, 3))
    alone[4] = 1.0
    L = np.stack(rows + [alone])
    effective, signal = adequacy.node_observation_strength(L, n_t, n_s)
    np.testing.assert_allclose(signal[0, 1:], [0.4, 0.6], rtol=1e-9)
    np.testing.assert_allclose(effective[0, 1:], [20.0, 20.0], rtol=1e-9)
    want = np.array([[True, False, True], [True, False, False]])

    def errors(estimate, observed_nodes):               # stands in for the metric: says which nodes it was given
        return {"eq1_observed": float(np.flatnonzero(observed_nodes).sum() + 100 * observed_nodes.sum())}

    truth = SimpleNamespace(errors=errors, floor="floor", exact="exact")
    rec = SimpleNamespace(lighting_matrix=L, brdf="recovered", solution=SimpleNamespace(measured=np.ones((2, 3, 3))))
    entry, nodes = protocol.score_recovery(rec, truth, (n_t, n_s))
    np.testing.assert_array_equal(nodes, want)
    assert entry["observed"]["nodes"] == 3 and entry["observed"]["node_fraction"] == pytest.approx(0.5)
    assert entry["recovered"]["eq1_observed"] == errors(None, want)["eq1_observed"]
    assert entry["grid_floor_observed"] == entry["exact_floor_observed"] == errors(None, want)["eq1_observed"]


def test_relight_scores_each_probe_with_its_own_truth_floor_and_noise(monkeypatch):
    """``relight`` under two novel probes (a stand-in renderer: the recovery renders 10 % above the truth under the
    first, 20 % under the second, whose truth is twice as bright; the exact reduction 5 % above under both): each
    render at that probe's seed (seed + 1 + k), scored against that probe's truth and floor, and the ratio kept
    only where the floor is at least twice that probe's own reference noise (1 %: ratio 2; 3 %: 0.05 < 0.06,
    null)."""
    from mi_bivariate.evaluate.renders import Shot

    truth, mask = np.ones((4, 4, 3)), np.ones((4, 4), bool)
    brightness, error = {"probe a": 1.0, "probe b": 2.0}, {"probe a": 1.1, "probe b": 1.2}
    seeds = []

    class StandIn:
        def render(self, bsdf, probe, name, resolution, seed, spp, cache_key=None):
            seeds.append((name, seed))
            return Shot(error[probe] * brightness[probe] * truth, mask, None)

    cfg = ev.EvalConfig(renderer="path", novel_probes=("a", "b"), seed=3)
    novel = protocol._Novel(truth={"a": Shot(truth, mask, None), "b": Shot(2.0 * truth, mask, None)},
                            floor={"a": 1.05 * truth, "b": 2.1 * truth}, floor_images={},
                            noise={"a": 0.01, "b": 0.03})
    monkeypatch.setattr(protocol, "plugin", lambda source, renderer: source)
    arrays = {}
    got = protocol.relight(StandIn(), cfg, SimpleNamespace(brdf="recovered"), ["probe a", "probe b"], novel, "in",
                           arrays)
    assert seeds == [("a", 4), ("b", 5)]
    assert got["a"] == pytest.approx({"rel_rmse": 0.1, "floor": 0.05, "ratio": 2.0, "psnr": 20.0}, rel=1e-9)
    assert {k: got["b"][k] for k in ("rel_rmse", "floor")} == pytest.approx({"rel_rmse": 0.2, "floor": 0.05})
    assert math.isnan(got["b"]["ratio"])
    assert got["b"]["psnr"] == pytest.approx(10.0 * math.log10(2.0 ** 2 / 0.4 ** 2), rel=1e-9)
    assert sorted(arrays) == ["recovered_render__in__a", "recovered_render__in__b"]
    np.testing.assert_array_equal(arrays["recovered_render__in__b"], np.float16(2.4))


def test_a_baseline_is_scored_as_its_3d_model(monkeypatch):
    """``fit_baselines`` scores each fit's full 3D model (the results' "GGX fit (3D)"), not its phi_d-averaged
    table, over the observed nodes, and saves the table (a stand-in fit and metric say what they were given)."""
    observed = np.eye(3, dtype=bool)
    fit = SimpleNamespace(summary=lambda: {"cost": 1.5}, brdf="3D model",
                          table=SimpleNamespace(table=np.full((3, 3, 3), 0.25)))
    monkeypatch.setattr(protocol.baselines, "fit_baselines", lambda *args, **kwargs: {"ggx": fit})
    truth = SimpleNamespace(errors=lambda estimate, observed_nodes: {"of": estimate, "nodes": observed_nodes})
    rec = SimpleNamespace(lighting_matrix=None, observations=SimpleNamespace(values=None))
    arrays = {}
    out = protocol.fit_baselines(rec, ev.EvalConfig(grid=(3, 3)), truth, observed, "in", arrays, {})
    assert out["ggx"]["cost"] == 1.5 and out["ggx"]["errors"]["of"] == "3D model"
    assert out["ggx"]["errors"]["nodes"] is observed
    np.testing.assert_array_equal(arrays["baseline__in__ggx"], np.full((3, 3, 3), 0.25))


def test_saved_renders_clip_to_the_float16_range():
    """The artifacts keep renders as float16, whose largest finite value is 65504: a brighter pixel (a sun's
    mirror image) is saved as 6e4, not as inf, so that a saved render stays finite where it is read back."""
    got = protocol._f16(np.array([1e5, 7e4, 1.5, 0.0]))
    assert got.dtype == np.float16
    np.testing.assert_array_equal(got, np.float16([6e4, 6e4, 1.5, 0.0]))


def _image(entry_rmse, psnr, floor, ratio):
    return {"rel_rmse": entry_rmse, "psnr": psnr, "floor": floor, "ratio": ratio}


def _record(name: str, scale: float = 1.0) -> dict:
    """A record as the protocol writes it, every number distinct (what summary_rows must pick up where)."""
    images = {"p1": _image(0.04, 30.0, 0.02, 2.0), "p2": _image(0.01, 40.0, 0.005, 2.0),
              "p3": _image(0.10, 26.0, 0.01, 10.0)}
    entry = {"recovered": {"eq1": 0.21 * scale, "eq1_min": 0.22, "cosine": 0.23, "log": 0.24,
                           "eq1_observed": 0.25, "observed_fraction": 0.7,
                           "regions": {"specular": {"eq1": 0.5, "share": 0.1}, "rest": {"eq1": 0.2, "share": 0.9}}},
             "baselines": {"ggx": {"errors": {"eq1": 0.31, "eq1_min": 0.32, "cosine": 0.33, "log": 0.34}}},
             "images": images, "grid_floor_observed": 0.3, "exact_floor_observed": 0.2,
             "confident": {"eq1": 0.5, "floor_eq1": 0.35, "exact_floor_eq1": 0.25, "node_fraction": 0.6},
             "relative_residual": 0.01, "adequacy": {"rank_fraction": 0.8, "adequate": True},
             "timings": {"solve": 1.0}}
    return {"material": name, "config_hash": "h", "inputs": {"in": entry},
            "floor": {"eq1": 0.11, "eq1_min": 0.12, "cosine": 0.13, "log": 0.14},
            "floors": {"exact_floor": 0.1 * scale, "grid_floor": 0.11, "exact_floor_min": 0.09, "grid_floor_min": 0.12},
            "floor_images": {"p1": {"rel_rmse": 0.02}, "p2": {"rel_rmse": 0.005}, "p3": {"rel_rmse": 0.01}},
            "reference_noise": {"p1": 1e-4, "p2": 3e-4, "p3": 2e-4}, "timings": {"total": 5.0}}


def test_summary_rows_and_medians_by_hand():
    """Each column of summary.csv from the record field of its name; the per-material relight columns are
    medians over the novel probes (the image columns means), and format_summary's are medians over materials."""
    (row,) = ev.summary_rows([_record("a")])
    want = {"floor_eq1": 0.11, "floor_eq1_min": 0.12, "floor_cosine": 0.13, "floor_log": 0.14,
            "recovered_eq1": 0.21, "recovered_eq1_min": 0.22, "recovered_cosine": 0.23, "recovered_log": 0.24,
            "ggx_eq1": 0.31, "ggx_eq1_min": 0.32, "ggx_cosine": 0.33, "ggx_log": 0.34,
            "image_rel_rmse_mean": 0.05, "image_psnr_mean": 32.0, "floor_image_rel_rmse_mean": 0.035 / 3,
            "reference_noise_max": 3e-4,
            "exact_floor": 0.1, "grid_floor": 0.11, "exact_floor_min": 0.09, "grid_floor_min": 0.12,
            "recovered_eq1_observed": 0.25, "grid_floor_observed": 0.3, "exact_floor_observed": 0.2,
            "observed_fraction": 0.7, "recovered_eq1_confident": 0.5, "grid_floor_confident": 0.35,
            "exact_floor_confident": 0.25, "confident_fraction": 0.6,
            "recovered_eq1_specular": 0.5, "recovered_share_rest": 0.9,
            "relight_rmse_median": 0.04, "relight_floor_median": 0.01, "relight_ratio_median": 2.0,
            "relight_p3": 0.10, "relight_floor_p3": 0.01}
    assert {k: row[k] for k in want} == pytest.approx(want, rel=1e-12)
    # Over materials: the median (0.21 of 0.105, 0.21, 2.1), not the mean (0.805).
    text = ev.format_summary([_record("a", 0.5), _record("b"), _record("c", 10.0)])
    assert "exact floor 0.100" in text and "relight/floor 2.000" in text, text
    assert ev.summary_rows([_record("c", 10.0)])[0]["recovered_eq1"] == pytest.approx(2.1)


def _rel_rmse_by_hand(image: np.ndarray, reference: np.ndarray, mask: np.ndarray) -> float:
    a, b = np.asarray(image, np.float64)[mask], np.asarray(reference, np.float64)[mask]
    return float(np.sqrt(np.mean((a - b) ** 2) / np.mean(b ** 2)))


def test_relight_numbers_recomputed_from_the_saved_tables(tmp_path):
    """Every image number of a record recomputed outside the protocol: the truth, the exact reduction and the
    saved recovered table rendered by the reference renderer under each novel probe at the protocol's seed for
    that probe (seed + 1 + k), the same seed for all three; the errors, their ratio and the PSNR written out
    with numpy; the reference noise from the second seed."""
    from mi_bivariate import reference

    material = "ggx:diffuse=0.2,specular=0.5,alpha=0.2"      # not bivariate: a relight floor above the noise
    cfg = ev.EvalConfig(input_probes=("synthetic:1",), novel_probes=("synthetic:7", "synthetic:3"), resolution=32,
                        novel_resolution=16, n_normals=300, n_dirs=1000, grid=(8, 8), baselines=(),
                        reference_directions=(64, 128, 64), seed=4)
    (record,) = ev.run_evaluation([material], tmp_path / "eval", config=cfg, progress=False, figures=False)
    arrays = ev.load_artifacts(ev.artifact_path(tmp_path / "eval", record))
    truth = ev.load_truth(ev.resolve_materials([material])[0])
    tables = {"truth": truth, "floor": BivariateBRDF.reduce(truth, n_t=8, n_s=8),
              "recovered": BivariateBRDF(arrays["recovered__synthetic:1"])}
    for k, name in enumerate(cfg.novel_probes):
        seed = cfg.seed + 1 + k
        probe = ev.load_probe(name)
        shots = {what: reference.render_reference(brdf, probe, 16, seed, cfg.reference_directions)
                 for what, brdf in tables.items()}
        mask, want = shots["truth"].mask, shots["truth"].image
        again = reference.render_reference(truth, probe, 16, seed + protocol.REFERENCE_NOISE_SEED_OFFSET,
                                           cfg.reference_directions).image
        got = record["inputs"]["synthetic:1"]["images"][name]
        rel, floor = (_rel_rmse_by_hand(shots[w].image, want, mask) for w in ("recovered", "floor"))
        assert got["rel_rmse"] == pytest.approx(rel, rel=1e-6)
        assert got["floor"] == pytest.approx(floor, rel=1e-6) and floor > metrics.MIN_RELIGHT_FLOOR
        assert record["floor_images"][name]["rel_rmse"] == pytest.approx(floor, rel=1e-6)
        mse = np.mean((shots["recovered"].image[mask].astype(np.float64) - want[mask]) ** 2)
        assert got["psnr"] == pytest.approx(10.0 * math.log10(float(want[mask].max()) ** 2 / mse), rel=1e-6)
        noise = _rel_rmse_by_hand(again, want, mask) / math.sqrt(2.0)
        assert record["reference_noise"][name] == pytest.approx(noise, rel=1e-6) and noise > 0
        # The ratio: the floor is above twice the reference's noise (references of 64 x 128 x 64 directions: at
        # 16 x 32 x 16 their noise, 9%, is above the floor, and the ratio is null, metrics.NOISE_FLOOR_FACTOR)
        assert floor >= 2.0 * noise, (floor, noise)
        assert got["ratio"] == pytest.approx(rel / floor, rel=1e-6)


def test_leave_one_out_keeps_the_material_out_of_both_priors(tmp_path, monkeypatch):
    """``evaluate`` on a shared MERL-NBRDF material (a development one and a training one) scores it with a
    smoothness prior and a basis prior learnt from the other materials only: both equal the priors learnt here
    from the tables without it, and neither names it."""
    from mi_bivariate import basis_prior, nbrdf

    names = [nbrdf.NBRDF_MATERIALS[0], nbrdf.NBRDF_TRAIN_MATERIALS[0], *nbrdf.ALL_NBRDF_MATERIALS[1:7]]
    rng, t = np.random.default_rng(0), np.linspace(0, 1, 8)[:, None, None]
    tables = {name: (0.1 + (1000.0 * np.exp(-(t / 0.1) ** 2) if k % 2 else 0.0))
              * np.exp(rng.normal(0.0, 0.1, (8, 8, 3))) for k, name in enumerate(names)}  # diffuse and glossy
    monkeypatch.setenv("MI_BIVARIATE_CACHE", str(tmp_path))
    monkeypatch.setattr(training_set, "reduced_tables", lambda n_t, n_s, data_dir=None: tables)
    for material in names[:2]:
        for cached in (False, True):                         # learnt, then read back from the cache
            task = protocol.MaterialTask(ev.MaterialSpec(material, "nbrdf", material), ev.EvalConfig(grid=(8, 8)))
            smooth, basis, said = protocol.choose_priors(task)
            assert said.startswith("leave-one-out")
            others = {k: v for k, v in tables.items() if k != material}
            assert material not in smooth.provenance["materials"] and material not in basis.materials
            assert sorted(smooth.provenance["materials"]) == sorted(basis.materials) == sorted(others)
            want_smooth, want_basis = prior.Prior.learn(others), basis_prior.BasisPrior.learn(others)
            for pair in want_smooth.pairs:
                np.testing.assert_array_equal(smooth.pairs[pair], want_smooth.pairs[pair])
            np.testing.assert_array_equal(basis.basis, want_basis.basis)
            np.testing.assert_array_equal(basis.mean, want_basis.mean)


def _script_folder(tmp_path):
    """An evaluation folder of three hand-made records (inputs grace, uffizi and both) for the page's scripts."""
    import json

    out = tmp_path / "eval"
    out.mkdir()
    config = {"config_hash": "h", "resolution": 32, "novel_resolution": 16, "grid": [8, 8], "renderer": "reference"}
    (out / "config.json").write_text(json.dumps(config))
    for name, scale in (("a", 0.5), ("b", 1.0), ("c", 10.0)):
        r = _record(name, scale)
        one = r["inputs"].pop("in")
        one["recovered"] = {k: (v * scale if isinstance(v, float) and k != "observed_fraction" else v)
                            for k, v in one["recovered"].items()}
        one["images"] = {"p1": _image(0.04, 30.0, 0.02, 1.0), "p2": _image(0.01, 40.0, 0.005, 2.0),
                         "p3": _image(0.10, 26.0, 0.01, 10.0)}
        other = json.loads(json.dumps(one))
        for v in other["images"].values():
            v["rel_rmse"] *= 2.0                                 # uffizi: twice grace's relight errors
        both = json.loads(json.dumps(one))
        for v in both["images"].values():
            v["rel_rmse"] *= 1.5                                 # both: between the two
        r["inputs"] = {"grace_latlong_1k": one, "uffizi_256": other, "grace_latlong_1k+uffizi_256": both}
        r["relight_floor"] = {k: v["rel_rmse"] for k, v in r["floor_images"].items()}
        r["floors"]["exact_floor"] = 0.1                         # the floors alike, the recoveries scaled
        ev.append_record(out / ev.RESULTS_FILE, r)
    return out


def test_issue9_targets_by_hand(tmp_path):
    """scripts/issue9_targets.py: medians over materials of each material's ratios (relight / floor: the median
    over the novel probes; Eq. 1 over the observed cells and over f > 1e-3 over the floor of the same cells)."""
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "scripts" / "issue9_targets.py"
    text = subprocess.run([sys.executable, str(script), str(_script_folder(tmp_path))], capture_output=True,
                          text=True, check=True).stdout
    medians = dict(line[2:].rsplit(": ", 1) for line in text.splitlines() if line.startswith("- "))
    # Per material: ratios 1, 2, 10 over the probes (median 2); the Eq. 1 ratios scale 0.5, 1, 10 (median 1).
    want = {"ratio 1 image": "2.00", "ratio 2 images": "2.00",
            "eq1 observed / exact floor": "2.50",                # 0.25 / 0.1
            "grid floor observed / exact floor": "3.00",         # 0.3 / 0.1
            "eq1 observed / exact floor there": "1.25",          # 0.25 / 0.2
            "eq1 confident / exact floor": "5.00",               # 0.5 / 0.1
            "eq1 confident / grid floor there": "1.43",          # 0.5 / 0.35
            "eq1 confident / exact floor there": "2.00",         # 0.5 / 0.25
            "eq1 f>1e-3 / exact floor (f>1e-3)": "2.44",         # 0.22 / 0.09
            "grid floor f>1e-3 / exact floor (f>1e-3)": "1.33",  # 0.12 / 0.09
            "confident cells (share)": "0.60",
            "2 images beat the better single": "0/3 (0%)"}       # both's errors 1.5x grace's
    assert {k: medians.get(k) for k in want} == want, text


def test_results_tables_by_hand(tmp_path):
    """scripts/results_tables.py: the medians over materials of the summary columns, per input probe, and the
    relighting per novel probe (medians over materials of each record's numbers)."""
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "scripts" / "results_tables.py"
    text = subprocess.run([sys.executable, str(script), str(_script_folder(tmp_path))], capture_output=True,
                          text=True, check=True).stdout
    lines = text.splitlines()
    medians = lines[lines.index("### Medians over materials") + 4]
    # exact floor, grid floor, rec. Eq. 1 (0.21 x 0.5, 1, 10), rec. Eq. 1 observed, exact floor observed, grid
    # floor observed, observed cells, rec. Eq. 1 confident (scaled), exact / grid floor confident, confident cells,
    # rec. Eq. 1 > 1e-3, cosine, log (scaled), relight, relight floor and ratio (medians over the novel probes).
    assert medians == ("| grace_latlong_1k | 0.100 | 0.110 | 0.210 | 0.250 | 0.200 | 0.300 | 0.700 | 0.500 | 0.250 "
                       "| 0.350 | 0.600 | 0.220 | 0.230 | 0.240 | 0.040 | 0.010 | 2.000 |"), text
    relight = next(line for line in lines if line.startswith("| uffizi_256 | ") and " / " in line)
    assert relight == "| uffizi_256 | 0.080 / 0.020 / 1.000 | 0.020 / 0.005 / 2.000 | 0.200 / 0.010 / 10.000 |", text
    baselines = [line for line in lines if line.startswith("| grace_latlong_1k | Eq. 1, observed cells |")]
    assert baselines == ["| grace_latlong_1k | Eq. 1, observed cells | 0.300 | 0.250 | nan | nan |"], text


def test_summary_rows_skip_null_ratios_and_infinite_psnrs():
    """A novel probe whose floor is below the references' noise has a null ratio (read back as NaN), and a relit
    image equal to the truth an infinite PSNR: the row's median ratio is over the other probes, its mean PSNR
    over the finite ones, not NaN or inf."""
    import json

    from mi_bivariate.common import finite_json

    record = _record("a")
    images = record["inputs"]["in"]["images"]
    images["p1"]["ratio"] = float("nan")                   # floor 0.02 below the references' noise
    images["p2"]["psnr"] = float("inf")
    stored = json.loads(json.dumps(finite_json(record)))  # as results.jsonl holds it
    assert stored["inputs"]["in"]["images"]["p1"]["ratio"] is None
    (row,) = ev.summary_rows([stored])
    assert row["relight_ratio_median"] == pytest.approx(6.0)          # median of 2 and 10
    assert row["image_psnr_mean"] == pytest.approx(28.0)              # mean of 30 and 26
    assert row["relight_rmse_median"] == pytest.approx(0.04)          # every probe's error still counts
    # Over materials: a material without any finite ratio is left out of the median, and said to be.
    none = json.loads(json.dumps(finite_json(_record("b"))))
    for v in none["inputs"]["in"]["images"].values():
        v["ratio"] = None
    text = ev.format_summary([stored, none, _record("c")])
    assert "relight/floor 4.000 (over 2 of 3 materials" in text, text   # median of 6 and 2

