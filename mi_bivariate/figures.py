"""The evaluation's figures (``mi-bivariate evaluate``): the paper's Figs. 3, 5, 6 and 7 and
the baselines, drawn from the results alone.

Each plot function takes the JSON records of ``results.jsonl`` and/or one
material's artifact arrays (``materials/<config hash>/<slug>.npz``), returns a
matplotlib figure, and never renders or recovers anything.
:func:`evaluation_figures` chooses the figures and the example material and
saves them (:func:`mi_bivariate.evaluate.make_figures` reads an output folder
and calls it). The recovery report and the demo figure are in
:mod:`mi_bivariate.report`, whose drawing helpers these figures share.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import numpy as np

from mi_bivariate.bivariate import BivariateBRDF
from mi_bivariate.common import PathLike, node_extent
from mi_bivariate.report import (
    exposure_of,
    incident_plane,
    plot_table,
    pyplot,
    save_figure,
    show_difference,
    show_image,
)

Artifacts = Dict[str, np.ndarray]


def evaluation_figures(records: Sequence[dict], artifacts: Dict[str, Artifacts], fig_dir: PathLike,
                       formats: Sequence[str] = ("png",), dpi: int = 100,
                       novel_probes: Optional[Sequence[str]] = None,
                       input_probes: Optional[Sequence[str]] = None) -> List[Path]:
    """Draw and save every evaluation figure; returns the files written.

    Figures (in ``fig_dir``): ``fig3_reduction``, ``fig5_validation``,
    ``fig6_incident``, ``fig6_errors``, ``fig7_environment``, ``tables``,
    ``baselines``; one file per format in ``formats`` (png, pdf). Fig. 5, 6
    (incident plane) and 7 show the median material by recovered log error
    under the first input probe; Figs. 3, 5 and 7 show the renders under the first novel probe.

    Args:
        records: the records of one configuration (at least one).
        artifacts: ``{material label: artifact arrays}`` of every record.
        novel_probes: the novel probes' labels in the configuration's order (``EvalConfig.novel_probes``,
            each by :func:`mi_bivariate.sources.probe_label`); ``None``: the order of the first record's
            ``floor_images`` (alphabetical once the record was read back from ``results.jsonl``).
        input_probes: the inputs' labels in the configuration's order (``EvalConfig.input_probes``, each by
            :func:`mi_bivariate.sources.input_label`); ``None``: the order of the first record's ``inputs``.
    """
    fig_dir = Path(fig_dir)
    written: List[Path] = []

    def save(fig: Any, stem: str) -> None:
        written.extend(save_figure_formats(fig, fig_dir / stem, formats, dpi=dpi))

    probes_in = list(input_probes) if input_probes else list(records[0]["inputs"])
    novel = list(novel_probes) if novel_probes else list(records[0]["floor_images"])
    save(plot_reduction_ranking(records, artifacts, novel[0]), "fig3_reduction")
    # Fig. 5: the median material by recovered error under the first input probe.
    order = sorted(records, key=lambda r: r["inputs"][probes_in[0]]["recovered"]["log"])
    example = order[len(order) // 2]
    art = artifacts[example["material"]]
    save(plot_validation(example, art, probes_in[0], novel[0]), "fig5_validation")
    save(plot_incident_planes(example, art, probes_in), "fig6_incident")
    save(plot_error_curves(records), "fig6_errors")
    save(plot_environment_dependence(example, art, probes_in, novel[0]), "fig7_environment")
    save(plot_table_gallery(records, artifacts, probes_in), "tables")
    save(plot_baselines(records, probes_in[0]), "baselines")
    return written


def save_figure_formats(fig: Any, stem: PathLike, formats: Sequence[str] = ("png",), dpi: int = 100) -> List[Path]:
    """Save one figure as ``stem.<fmt>`` for every format (atomic, :func:`report.save_figure`), then close it."""
    stem = Path(stem)
    paths = [save_figure(fig, stem.with_name(f"{stem.name}.{fmt}"), dpi=dpi, close=False) for fmt in formats]
    pyplot().close(fig)
    return paths


def _f32(image: np.ndarray) -> np.ndarray:
    return np.asarray(image, np.float32)


def _material_order(records: Sequence[dict], key: Any) -> list:
    return sorted(records, key=key)


_METRIC_LABELS = {"eq1": "Eq. 1 relative RMS", "eq1_min": "Eq. 1, cells f > 1e-3 1/sr",
                  "cosine": "cosine-weighted relative L2", "log": "RMS of ln(1 + f) difference"}


def _grid_name(records: Sequence[dict]) -> str:
    """``"n_t x n_s"`` of the records' reduced tables (``record["floors"]["grid"]``), else ``"reduced"``."""
    grids = {tuple(r.get("floors", {}).get("grid", ())) for r in records}
    grid = grids.pop() if len(grids) == 1 else ()
    return f"{grid[0]} x {grid[1]}" if len(grid) == 2 else "reduced"


def plot_reduction_ranking(records: Sequence[dict], artifacts: Dict[str, Dict[str, np.ndarray]],
                           novel: str, metric: str = "eq1") -> Any:
    """Fig. 3 analogue: materials sorted by the error of their bivariate reduction.

    Top (log scale): the paper's Fig. 3 curve, the *exact floor* (Eq. 1 of the phi_d average at MERL
    resolution; ``record["floors"]``), over all cells and over f > 1e-3, and beside it the *grid
    floor* of the reduced table read back (``record["floor"]``: Eq. 1 and the other metrics), dashed.
    Materials are sorted by the exact floor's Eq. 1 (``metric="eq1"``; another metric sorts by the
    grid table's). Bottom: the best and the worst material rendered under the probe ``novel`` with
    the full 3D BRDF and with its reduced table. Records without ``floors`` (before stop 25) draw
    the grid floor alone.
    """
    plt = pyplot()
    grid = _grid_name(records)
    exact = all("exact_floor" in r.get("floors", {}) for r in records)
    if exact and metric == "eq1":
        order = _material_order(records, lambda r: r["floors"]["exact_floor"])
    else:
        order = _material_order(records, lambda r: r["floor"][metric])
    fig = plt.figure(figsize=(12, 7.5))
    ax = fig.add_subplot(2, 1, 1)
    x = np.arange(len(order))
    if exact:
        for key, style, label in (("exact_floor", "o-", "exact floor (phi_d average): Eq. 1"),
                                  ("exact_floor_min", "s-", "exact floor: Eq. 1, cells f > 1e-3 1/sr")):
            ax.semilogy(x, [max(r["floors"][key], 1e-6) for r in order], style, ms=4, lw=1.2, label=label)
    for m, style in zip(("eq1", "eq1_min", "cosine", "log"), ("o--", "s--", "^:", "d:")):
        ax.semilogy(x, [max(r["floor"][m], 1e-6) for r in order], style, ms=3, lw=0.8, alpha=0.8,
                    label=f"grid floor ({grid} table): {_METRIC_LABELS[m]}")
    ax.set_xticks(x, [r["material"] for r in order], rotation=60, ha="right", fontsize=7)
    ax.set_ylabel("error of the bivariate reduction", fontsize=8)
    sort_label = ("the exact floor's Eq. 1" if exact and metric == "eq1"
                  else f"the grid table's {_METRIC_LABELS[metric]}")
    ax.set_title(f"bivariate reduction of each material (paper Fig. 3: the exact floor), sorted by {sort_label}",
                 fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=6, ncol=2)
    for k, (r, tag) in enumerate(((order[0], "best"), (order[-1], "worst"))):
        art = artifacts[r["material"]]
        truth, floor, mask = _f32(art[f"truth__{novel}"]), _f32(art[f"floor_render__{novel}"]), art["mask"]
        exposure = exposure_of(truth, mask)
        show_image(fig.add_subplot(2, 4, 5 + 2 * k), truth, f"{tag}: {r['material']}\n3D truth ({novel})", exposure)
        show_image(fig.add_subplot(2, 4, 6 + 2 * k), floor,
                   f"{grid} reduction\n(grid floor: Eq. 1 {r['floor']['eq1']:.3g}, log {r['floor']['log']:.3g})",
                   exposure)
    fig.tight_layout()
    return fig


def plot_validation(record: dict, art: Dict[str, np.ndarray], input_probe: str, novel: str) -> Any:
    """Fig. 5 analogue: input image, recovered re-render, ground truth, |difference| x100 under ``novel``."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 4, figsize=(15, 3.9))
    mask = art["mask"]
    image = _f32(art[f"input__{input_probe}"])
    show_image(axes[0], image, f"input: {record['material']}\nunder {input_probe}", exposure_of(image, mask))
    truth = _f32(art[f"truth__{novel}"])
    rec = _f32(art[f"recovered_render__{input_probe}__{novel}"])
    exposure = exposure_of(truth, mask)
    errs = record["inputs"][input_probe]["images"][novel]
    show_image(axes[1], rec, f"recovered, novel probe {novel}", exposure)
    show_image(axes[2], truth, "ground truth (3D table)", exposure)
    show_difference(axes[3], rec, truth, mask,
                f"|difference| x100 / mean\nrel. RMSE {errs['rel_rmse']:.3f}, PSNR {errs['psnr']:.1f} dB")
    fig.tight_layout()
    return fig


def _table_eval(table: np.ndarray, theta_h: np.ndarray, theta_d: np.ndarray) -> np.ndarray:
    return BivariateBRDF(np.asarray(table, np.float32)).eval(theta_h, theta_d)


def plot_incident_planes(record: dict, art: Dict[str, np.ndarray], input_probes: Sequence[str],
                         channel: int = 1) -> Any:
    """Fig. 6 analogue (scatter): the BRDF along the incident plane for the stored view angles.

    Curves: the original 3D BRDF, its bivariate reduction (truth), and the
    table recovered under each input probe (one channel, log scale).
    """
    plt = pyplot()
    views = sorted(float(k.split("__")[1]) for k in art if k.startswith("incident__") and k.endswith("__truth"))
    fig, axes = plt.subplots(1, len(views), figsize=(6 * len(views), 4), squeeze=False)
    theta_in = art["incident__theta_in"]
    for ax, view in zip(axes[0], views):
        _, theta_h, theta_d, _ = incident_plane(view, n=len(theta_in))
        ax.plot(theta_in, art[f"incident__{view:g}__truth"][:, channel], "k.", ms=3, label="original 3D")
        ax.plot(theta_in, _table_eval(art["floor"], theta_h, theta_d)[:, channel], "-", lw=1.5,
                label="bivariate truth (floor)")
        for p, style in zip(input_probes, ("--", "-.", ":")):
            ax.plot(theta_in, _table_eval(art[f"recovered__{p}"], theta_h, theta_d)[:, channel], style, lw=1.3,
                    label=f"recovered ({p})")
        ax.set_yscale("log")
        ax.set_xlabel(f"light angle in the incident plane (deg), view at {view:g} deg", fontsize=8)
        ax.set_ylabel(f"f ({'RGB'[channel]}, 1/sr)", fontsize=8)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"{record['material']}: incident plane", fontsize=10)
    fig.tight_layout()
    return fig


def plot_error_curves(records: Sequence[dict], metrics: Sequence[str] = ("eq1", "cosine", "log")) -> Any:
    """Fig. 6 analogue (curves): per-material error for each input probe over the bivariate floor.

    Materials are sorted by the floor's error of each panel's metric.
    """
    plt = pyplot()
    probes = list(records[0]["inputs"])
    fig, axes = plt.subplots(1, len(metrics), figsize=(6 * len(metrics), 4.2), squeeze=False)
    for ax, m in zip(axes[0], metrics):
        order = _material_order(records, lambda r: r["floor"][m])
        x = np.arange(len(order))
        ax.fill_between(x, 1e-6, [max(r["floor"][m], 1e-6) for r in order], color="0.85",
                        label=f"grid floor ({_grid_name(records)} reduction)")
        for p, style in zip(probes, ("o-", "s--", "^:")):
            ax.plot(x, [max(r["inputs"][p]["recovered"][m], 1e-6) for r in order], style, ms=3, lw=1,
                    label=f"recovered ({p})")
        ax.set_yscale("log")
        ax.set_xticks(x, [r["material"] for r in order], rotation=70, ha="right", fontsize=6)
        ax.set_title(_METRIC_LABELS[m], fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def _observation_image(ax: Any, omap: np.ndarray, title: str) -> None:
    im = ax.imshow(np.log10(np.maximum(omap, 1e-3)), origin="lower", extent=node_extent(*omap.shape[:2]),
                   cmap="cividis", aspect="auto")
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(0.0, 1.0)
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("s = 2 theta_d / pi", fontsize=8)
    ax.set_ylabel("t = sqrt(2 theta_h / pi)", fontsize=8)
    ax.figure.colorbar(im, ax=ax, fraction=0.046, pad=0.02, label="log10 observations")


def plot_environment_dependence(record: dict, art: Dict[str, np.ndarray], input_probes: Sequence[str],
                                novel: Optional[str] = None) -> Any:
    """Fig. 7 analogue: one material recovered under each input probe, with the adequacy map.

    Row per input probe: input image, st observation map (adequacy), recovered
    table, bivariate truth, re-render under the novel probe ``novel`` (a label; ``None``: the first
    of the record's ``floor_images``, as :func:`evaluation_figures` picks it without the configuration).
    """
    plt = pyplot()
    if novel is None:
        novel = next(iter(record["floor_images"]))
    floor = BivariateBRDF(np.asarray(art["floor"], np.float32))
    lo = float(np.log10(max(np.percentile(floor.table, 1), 1e-4)))
    hi = float(np.log10(max(floor.table.max(), 1e-3)))
    fig, axes = plt.subplots(len(input_probes), 5, figsize=(22, 4 * len(input_probes)), squeeze=False)
    mask = art["mask"]
    for row, p in zip(axes, input_probes):
        e = record["inputs"][p]
        a = e["adequacy"]
        image = _f32(art[f"input__{p}"])
        show_image(row[0], image, f"input under {p}", exposure_of(image, mask))
        _observation_image(row[1], art[f"observation_map__{p}"],
                           f"adequacy: rank {a['rank_fraction']:.2f}, cond {a['condition_number']:.2g}"
                           + ("" if a["adequate"] else " (flagged)"))
        r = e["recovered"]
        plot_table(row[2], BivariateBRDF(np.asarray(art[f"recovered__{p}"], np.float32)),
                   f"recovered (log err {r['log']:.3f}, Eq. 1 {r['eq1']:.3g})", vmin=lo, vmax=hi)
        plot_table(row[3], floor, f"bivariate truth (log err {record['floor']['log']:.3f})", vmin=lo, vmax=hi)
        truth = _f32(art[f"truth__{novel}"])
        show_image(row[4], _f32(art[f"recovered_render__{p}__{novel}"]),
              f"re-render under {novel} (rel. RMSE {e['images'][novel]['rel_rmse']:.3f})", exposure_of(truth, mask))
    fig.suptitle(f"{record['material']}: the same material recovered under different environments", fontsize=11)
    fig.tight_layout()
    return fig


def plot_table_gallery(records: Sequence[dict], artifacts: Dict[str, Dict[str, np.ndarray]],
                       input_probes: Sequence[str], columns: int = 2) -> Any:
    """(theta_h, theta_d) images (log10 mean RGB) of every recovered table next to the bivariate truth.

    Per material: truth, then one panel per input probe, on a shared colour
    scale (x: theta_d, y: t ~ sqrt(theta_h), specular peak at the bottom).
    """
    plt = pyplot()
    n = len(records)
    per = 1 + len(input_probes)
    rows = int(np.ceil(n / columns))
    fig, axes = plt.subplots(rows, columns * per, figsize=(1.9 * columns * per, 1.75 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.set_axis_off()
    for k, r in enumerate(records):
        art = artifacts[r["material"]]
        floor = np.asarray(art["floor"], np.float64).mean(axis=2)
        lo = float(np.log10(max(np.percentile(floor, 1), 1e-4)))
        hi = float(np.log10(max(floor.max(), 1e-3)))
        tables = [("truth", floor)] + [(p, np.asarray(art[f"recovered__{p}"], np.float64).mean(axis=2))
                                       for p in input_probes]
        for j, (label, table) in enumerate(tables):
            ax = axes[k // columns, (k % columns) * per + j]
            ax.imshow(np.log10(np.maximum(table, 1e-4)), origin="lower", extent=node_extent(*table.shape),
                      cmap="viridis", vmin=lo, vmax=hi, aspect="auto")
            ax.set_xlim(0.0, 1.0)
            ax.set_ylim(0.0, 1.0)
            ax.set_title((r["material"][:22] + "\n" if j == 0 else "\n") + label, fontsize=6)
    fig.tight_layout()
    return fig


def plot_baselines(records: Sequence[dict], input_probe: str, metrics: Sequence[str] = ("log", "eq1_min")) -> Any:
    """Per-material errors of the bivariate recovery, the parametric baselines and the floor."""
    plt = pyplot()
    families = list(records[0]["inputs"][input_probe].get("baselines", {}))
    fig, axes = plt.subplots(len(metrics), 1, figsize=(13, 3.6 * len(metrics)), squeeze=False)
    for ax, m in zip(axes[:, 0], metrics):
        order = _material_order(records, lambda r: r["inputs"][input_probe]["recovered"][m])
        x = np.arange(len(order))
        series = [("bivariate recovery", [r["inputs"][input_probe]["recovered"][m] for r in order])]
        series += [(f"{f} fit (3D)", [r["inputs"][input_probe]["baselines"][f]["errors"][m] for r in order])
                   for f in families]
        series.append((f"grid floor ({_grid_name(records)} reduction)", [r["floor"][m] for r in order]))
        width = 0.8 / len(series)
        for k, (label, values) in enumerate(series):
            ax.bar(x + (k - (len(series) - 1) / 2) * width, np.maximum(values, 1e-6), width, label=label)
        ax.set_yscale("log")
        ax.set_xticks(x, [r["material"] for r in order], rotation=60, ha="right", fontsize=7)
        ax.set_ylabel(_METRIC_LABELS[m], fontsize=8)
        ax.grid(True, axis="y", which="both", alpha=0.3)
        ax.legend(fontsize=7, ncol=len(series))
    axes[0, 0].set_title(f"bivariate recovery vs parametric fits, input probe {input_probe}", fontsize=9)
    fig.tight_layout()
    return fig
