"""The evaluation's figures (mi_bivariate.figures) say what the records and artifacts hold: which material
each figure shows, in which order, which numbers and which images, checked on a small hand-made
evaluation whose every value is known (no rendering or recovery)."""

from __future__ import annotations

import numpy as np
import pytest

from mi_bivariate import figures

METRICS = ("eq1", "eq1_min", "cosine", "log")
PROBES_IN = ("grace", "uffizi")
NOVEL = ("pisa", "venice")
SIZE = 8                                  # renders SIZE x SIZE px; tables 4 x 4


def _errors(base: float) -> dict:
    """Four metric values whose order over the materials differs from metric to metric."""
    return {m: base * (1.0 + k) if k % 2 == 0 else 1.0 / (base * (1.0 + k)) for k, m in enumerate(METRICS)}


def _fake_evaluation():
    """Records and artifacts of three materials with distinct, known numbers and images.

    Under the first input probe the recovered log error ranks the materials b < c < a (median: c), and
    its eq1 ranks them otherwise (median: a); the exact floor ranks them a < b < c; the grid floor's
    eq1 ranks them c < b < a. The recovered re-render under each novel probe is twice the truth.
    """
    rng = np.random.default_rng(3)
    records, artifacts = [], {}
    log = {"a": 0.3, "b": 0.1, "c": 0.2}
    eq1 = {"a": 2.0, "b": 3.0, "c": 1.0}
    for k, name in enumerate("abc"):
        inputs = {}
        for j, p in enumerate(PROBES_IN):
            recovered = _errors(0.5 + k + 3 * j)
            recovered.update(log=log[name] + j, eq1=eq1[name] + j)
            inputs[p] = {"recovered": recovered,
                         "images": {n: {"rel_rmse": 0.111 * (k + 1) + 0.01 * i, "psnr": 30.0 + k}
                                    for i, n in enumerate(NOVEL)},
                         "adequacy": {"rank_fraction": 0.5, "condition_number": 1e3, "adequate": name != "b"},
                         "baselines": {"ggx": {"errors": _errors(2.0 + k)}, "ward": {"errors": _errors(3.0 + k)}}}
        records.append({"material": name, "inputs": inputs, "floor": _errors(3.0 - k),
                        "floors": {"exact_floor": 0.01 * (k + 1), "exact_floor_min": 0.02 * (k + 1), "grid": [4, 4]},
                        "floor_images": {n: {"rel_rmse": 0.05} for n in NOVEL}})
        mask = np.zeros((SIZE, SIZE), bool)
        mask[2:6, 1:7] = True
        art = {"mask": mask, "incident__theta_in": np.linspace(-89.5, 89.5, 19)}
        t = np.linspace(0.0, 1.0, 4)[:, None, None]
        table = 10.0 ** (-2.0 * t - 0.2 * k) * np.array([0.5, 1.0, 1.5]) * np.ones((4, 4, 3))
        art["floor"] = table.astype(np.float32)
        for j, p in enumerate(PROBES_IN):
            art[f"recovered__{p}"] = (art["floor"] * (1.0 + 0.5 * j)).astype(np.float32)
            art[f"input__{p}"] = (rng.random((SIZE, SIZE, 3)) * mask[..., None]).astype(np.float32)
            art[f"observation_map__{p}"] = 10.0 ** rng.uniform(-2, 1, (4, 4))
        for n in NOVEL:
            truth = (0.1 + rng.random((SIZE, SIZE, 3))) * mask[..., None]
            art[f"truth__{n}"] = truth.astype(np.float32)
            art[f"floor_render__{n}"] = (1.5 * truth).astype(np.float32)
            for p in PROBES_IN:
                art[f"recovered_render__{p}__{n}"] = (2.0 * truth).astype(np.float32)
        for view in (30.0, 60.0):
            art[f"incident__{view:g}__truth"] = np.tile([0.1, 0.2, 0.3], (19, 1)) * (1.0 + view)
        artifacts[name] = art
    return records, artifacts


@pytest.fixture()
def evaluation():
    return _fake_evaluation()


@pytest.fixture()
def close_figures():
    yield
    figures.pyplot().close("all")


def _titles(fig) -> list:
    return [ax.get_title() for ax in fig.axes]


def test_the_example_figures_show_the_median_material_by_recovered_log_error(evaluation, tmp_path, monkeypatch):
    """Figs. 5, 6 (incident plane) and 7 show the median material by recovered log error under the first
    input probe (c), not the first (b) nor the median by another metric (a), and each figure is saved
    under its name in every format asked for (the drawing itself is the other tests')."""
    records, artifacts = evaluation
    shown, saved = {}, []
    for name in ("plot_validation", "plot_incident_planes", "plot_environment_dependence", "plot_reduction_ranking",
                 "plot_error_curves", "plot_table_gallery", "plot_baselines"):
        monkeypatch.setattr(figures, name, lambda *args, name=name, **kwargs: shown.setdefault(name, args))
    monkeypatch.setattr(figures, "save_figure_formats",
                        lambda fig, stem, formats, dpi: saved.extend(f"{stem.name}.{f}" for f in formats) or [])
    figures.evaluation_figures(records, artifacts, tmp_path, formats=("png", "pdf"))
    assert sorted(saved) == sorted(f"{stem}.{fmt}" for stem in (
        "fig3_reduction", "fig5_validation", "fig6_incident", "fig6_errors", "fig7_environment", "tables",
        "baselines") for fmt in ("png", "pdf"))
    for name in ("plot_validation", "plot_incident_planes", "plot_environment_dependence"):
        record, art = shown[name][:2]
        assert record["material"] == "c" and art is artifacts["c"], name
    assert shown["plot_validation"][2:] == ("grace", "pisa")


def test_a_figure_is_saved_in_every_format(tmp_path, close_figures):
    fig = figures.pyplot().figure(figsize=(1, 1))
    paths = figures.save_figure_formats(fig, tmp_path / "f", ("png", "pdf"), dpi=10)
    assert [p.name for p in paths] == ["f.png", "f.pdf"]
    assert paths[0].read_bytes().startswith(b"\x89PNG") and paths[1].read_bytes().startswith(b"%PDF")


def test_reduction_ranking_shows_the_best_and_worst_by_the_exact_floor(evaluation, close_figures):
    records, artifacts = evaluation
    fig = figures.plot_reduction_ranking(records, artifacts, "pisa")
    curves = {line.get_label(): line.get_ydata() for line in fig.axes[0].get_lines()}
    titles = [t for t in _titles(fig)[1:] if t]
    assert titles[0].startswith("best: a\n") and titles[2].startswith("worst: c\n"), titles
    # every grid-floor curve holds its own metric, in the exact floor's order (a, b, c)
    for m, label in figures._METRIC_LABELS.items():
        np.testing.assert_allclose(curves[f"grid floor (4 x 4 table): {label}"], [r["floor"][m] for r in records])
    assert len(set(figures._METRIC_LABELS.values())) == len(METRICS)
    # one record without the exact floor (before stop 25): the grid floor alone, sorted by its eq1
    old = [dict(r) for r in records]
    del old[0]["floors"]
    fig = figures.plot_reduction_ranking(old, artifacts, "pisa")
    labels = [line.get_label() for line in fig.axes[0].get_lines()]
    assert not any(label.startswith("exact floor") for label in labels), labels
    assert "sorted by the grid table's" in fig.axes[0].get_title()
    # tables of two grids are not named by one of them
    old[1]["floors"] = {"grid": [8, 8]}
    assert figures._grid_name(old) == "reduced" and figures._grid_name(records) == "4 x 4"


def test_validation_shows_the_difference_to_the_truth_at_one_exposure(evaluation, close_figures):
    """Fig. 5: the difference panel is |recovered - truth| over the truth's mean on the object, x100 (here the
    recovered render is twice the truth T: T / mean(T) x 100 per pixel, not a difference to the input), the
    recovered render is shown at the truth's exposure, and the title's numbers are the record's."""
    records, artifacts = evaluation
    art = artifacts["c"]
    fig = figures.plot_validation(records[2], art, "grace", "pisa")
    truth, mask = art["truth__pisa"].astype(np.float64), art["mask"]
    shown = np.ma.filled(fig.axes[3].images[0].get_array(), np.nan)
    np.testing.assert_allclose(shown[mask], truth.mean(axis=2)[mask] / truth[mask].mean() * 100.0, rtol=1e-5)
    assert np.isnan(shown[~mask]).all()
    assert "rel. RMSE 0.333, PSNR 32.0 dB" in fig.axes[3].get_title()
    recovered_shown = fig.axes[1].images[0].get_array()
    truth_panel = figures.pyplot().figure()
    figures.show_image(truth_panel.add_subplot(), 2.0 * truth, "", figures.exposure_of(truth, mask))
    np.testing.assert_array_equal(recovered_shown, truth_panel.axes[0].images[0].get_array())


def test_incident_planes_plot_each_view_and_the_channel_asked(evaluation, close_figures):
    """The bivariate truth along the incident plane of view v, in the channel asked: light and view in
    one plane at signed angles theta_in and v have theta_h = |theta_in + v| / 2 (0 at the mirror
    direction), read here from a table that varies along t only, linearly between its nodes."""
    records, artifacts = evaluation
    art = artifacts["a"]
    fig = figures.plot_incident_planes(records[0], art, PROBES_IN, channel=1)
    theta_in = art["incident__theta_in"]
    nodes = np.linspace(0.0, 1.0, 4)
    for ax, view in zip(fig.axes, (30.0, 60.0)):
        lines = {line.get_label(): line for line in ax.get_lines()}
        np.testing.assert_allclose(lines["original 3D"].get_ydata(), 0.2 * (1.0 + view))
        t = np.sqrt(2.0 * np.radians(np.abs(theta_in + view) / 2.0) / np.pi)
        green = np.interp(t, nodes, 10.0 ** (-2.0 * nodes))
        np.testing.assert_allclose(lines["bivariate truth (floor)"].get_ydata(), green, rtol=1e-5)
        np.testing.assert_allclose(lines["recovered (uffizi)"].get_ydata(), 1.5 * green, rtol=1e-5)
        assert ax.get_ylabel() == "f (G, 1/sr)"


def test_error_curves_sort_each_metric_by_its_own_floor(evaluation, close_figures):
    records, _ = evaluation
    fig = figures.plot_error_curves(records, metrics=("eq1", "log"))        # the floors' orders differ
    for ax, m in zip(fig.axes, ("eq1", "log")):
        order = sorted(records, key=lambda r: r["floor"][m])
        assert [t.get_text() for t in ax.get_xticklabels()] == [r["material"] for r in order]
        lines = {line.get_label(): line.get_ydata() for line in ax.get_lines()}
        for p in PROBES_IN:
            np.testing.assert_allclose(lines[f"recovered ({p})"], [r["inputs"][p]["recovered"][m] for r in order])
        assert ax.get_title() == figures._METRIC_LABELS[m]


def test_environment_figure_shows_the_recovered_tables_and_the_adequacy_flags(evaluation, close_figures):
    records, artifacts = evaluation
    art = artifacts["b"]
    fig = figures.plot_environment_dependence(records[1], art, PROBES_IN[1:])
    panels = [ax for ax in fig.axes if ax.get_title()]          # the colour bars have no title
    for row, p in ((panels, PROBES_IN[1]),):
        assert row[1].get_title().endswith("(flagged)")          # material b is inadequate under every probe
        np.testing.assert_allclose(row[1].images[0].get_array(), np.log10(art[f"observation_map__{p}"]))
        np.testing.assert_allclose(row[2].images[0].get_array(),
                                   np.log10(art[f"recovered__{p}"].astype(np.float64).mean(axis=2)), rtol=1e-5)
        assert row[4].get_title().startswith("re-render under pisa (")     # the first novel probe by name
    fig = figures.plot_environment_dependence(records[0], artifacts["a"], PROBES_IN[:1])
    assert not any(ax.get_title().endswith("(flagged)") for ax in fig.axes)


def test_table_gallery_shows_mean_rgb_on_a_scale_that_holds_the_truth(evaluation, close_figures):
    records, artifacts = evaluation
    fig = figures.plot_table_gallery(records, artifacts, PROBES_IN, columns=2)
    shown = [ax for ax in fig.axes if ax.images]
    assert len(shown) == len(records) * (1 + len(PROBES_IN))
    truth = np.log10(artifacts["a"]["floor"].astype(np.float64).mean(axis=2))
    np.testing.assert_allclose(shown[0].images[0].get_array(), truth, rtol=1e-5)
    lo, hi = shown[0].images[0].get_clim()
    assert np.mean((truth >= lo) & (truth <= hi)) >= 0.9            # the scale is the truth's range


def test_baselines_bars_hold_each_metric_centred_on_their_material(evaluation, close_figures):
    records, _ = evaluation
    fig = figures.plot_baselines(records, "grace", metrics=("log", "eq1_min"))
    for ax, m in zip(fig.axes, ("log", "eq1_min")):
        order = sorted(records, key=lambda r: r["inputs"]["grace"]["recovered"][m])
        assert [t.get_text() for t in ax.get_xticklabels()] == [r["material"] for r in order]
        bars = {c.get_label(): c for c in ax.containers}
        expected = {"bivariate recovery": [r["inputs"]["grace"]["recovered"][m] for r in order],
                    "ggx fit (3D)": [r["inputs"]["grace"]["baselines"]["ggx"]["errors"][m] for r in order],
                    "ward fit (3D)": [r["inputs"]["grace"]["baselines"]["ward"]["errors"][m] for r in order],
                    "grid floor (4 x 4 reduction)": [r["floor"][m] for r in order]}
        assert set(bars) == set(expected)
        centres = []
        for label, values in expected.items():
            np.testing.assert_allclose([b.get_height() for b in bars[label]], values)
            centres.append([b.get_x() + b.get_width() / 2 for b in bars[label]])
        np.testing.assert_allclose(np.mean(centres, axis=0), np.arange(len(order)), atol=1e-12)


def test_figs_3_5_and_7_show_the_configurations_first_novel_probe(evaluation, tmp_path, monkeypatch,
                                                                    close_figures):
    """Fig. 7 re-rendered under the alphabetically first novel probe (the artifacts' sorted names) and Figs. 3
    and 5 under the record's first: with --novel-probes venice pisa they could show two probes. Given the
    configuration's order, all three show its first (venice); without it, the record's first (pisa). Fig. 7's
    re-render panel is the material's render under that probe, with that probe's numbers."""
    records, artifacts = evaluation
    shown = {}
    for name in ("plot_validation", "plot_incident_planes", "plot_environment_dependence", "plot_reduction_ranking",
                 "plot_error_curves", "plot_table_gallery", "plot_baselines"):
        monkeypatch.setattr(figures, name, lambda *args, name=name, **kwargs: shown.setdefault(name, args))
    monkeypatch.setattr(figures, "save_figure_formats", lambda *args, **kwargs: [])
    for novel_probes, first in ((("venice", "pisa"), "venice"), (None, "pisa")):
        shown.clear()
        figures.evaluation_figures(records, artifacts, tmp_path, novel_probes=novel_probes)
        assert (shown["plot_reduction_ranking"][2], shown["plot_validation"][3],
                shown["plot_environment_dependence"][3]) == (first,) * 3, novel_probes
    # The inputs likewise: given the configuration's order (uffizi, grace), Figs. 5-7, the gallery and the
    # baselines take uffizi first, and Fig. 5's material is the median under uffizi (log errors +1: still c).
    for input_probes, order in ((("uffizi", "grace"), ["uffizi", "grace"]), (None, ["grace", "uffizi"])):
        shown.clear()
        figures.evaluation_figures(records, artifacts, tmp_path, input_probes=input_probes)
        assert shown["plot_validation"][2] == order[0] and shown["plot_baselines"][1] == order[0]
        assert [list(shown[name][2]) for name in ("plot_incident_planes", "plot_environment_dependence",
                                                  "plot_table_gallery")] == [order] * 3
        assert shown["plot_validation"][0]["material"] == "c"
    monkeypatch.undo()
    art = artifacts["b"]
    fig = figures.plot_environment_dependence(records[1], art, PROBES_IN[1:], "venice")
    panel = [ax for ax in fig.axes if ax.get_title()][4]
    assert panel.get_title() == "re-render under venice (rel. RMSE 0.232)"   # material b: 0.111 x 2 + 0.01
    expected = figures.pyplot().figure()
    figures.show_image(expected.add_subplot(), art["recovered_render__uffizi__venice"], "",
                       figures.exposure_of(art["truth__venice"], art["mask"]))
    np.testing.assert_array_equal(panel.images[0].get_array(), expected.axes[0].images[0].get_array())


def test_make_figures_passes_the_configurations_probe_order(evaluation, tmp_path, monkeypatch):
    """Records come back from results.jsonl with their keys sorted (floor_images: pisa, venice): make_figures
    takes the novel probes' and the inputs' order from config.json (probe files by their labels), for records
    of its configuration only."""
    import json

    from mi_bivariate.evaluate import results

    records, artifacts = evaluation
    out = tmp_path / "e"
    out.mkdir()
    for r in records:
        results.append_record(out / results.RESULTS_FILE, {**r, "config_hash": "h", "slug": r["material"]})
    passed = []
    monkeypatch.setattr(results, "load_artifacts", lambda path: artifacts[path.stem])
    monkeypatch.setattr(results, "evaluation_figures", lambda recs, arts, fig_dir, **kwargs: passed.append(
        (list(recs[0]["floor_images"]), kwargs["novel_probes"], kwargs["input_probes"])) or [])
    ours = {"config_hash": "h", "novel_probes": ["/probes/venice.hdr", "pisa"], "input_probes": ["/p/uffizi.exr", "grace"]}
    for config, novel, inputs in ((ours, ["venice", "pisa"], ["uffizi", "grace"]),
                                  ({**ours, "config_hash": "other"}, None, None),
                                  ("not a config", None, None)):
        (out / "config.json").write_text(json.dumps(config))
        results.make_figures(out, results.read_records(out / results.RESULTS_FILE, "h"))
        assert passed[-1] == (["pisa", "venice"], novel, inputs)
    (out / "config.json").write_text(json.dumps({"config_hash": "h", "novel_probes": ["venice", "pisa"],
                                                 "input_probes": ["uffizi", "grace"]}))
    results.make_figures(out)                                   # records read by make_figures itself
    assert passed[-1] == (["pisa", "venice"], ["venice", "pisa"], ["uffizi", "grace"]) and len(passed) == 4
