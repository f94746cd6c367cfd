"""Figures: the recovery report (PNG) and the demo figure.

matplotlib with the non-interactive Agg backend; every file is written
atomically. Images are shown tonemapped with one exposure per row so that
recovered and reference renders are directly comparable.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, Optional, Sequence, Tuple

import numpy as np

from mi_bivariate.atomic import atomic_path
from mi_bivariate.bivariate import BivariateBRDF
from mi_bivariate.coordinates import half_diff_from_dirs
from mi_bivariate.images import tonemap
from mi_bivariate.common import PathLike
from mi_bivariate import render



def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, path: PathLike, dpi: int = 110, tight: bool = True) -> Path:
    """Save a matplotlib figure atomically (format from the suffix) and close it.

    ``tight=False`` skips ``bbox_inches="tight"`` (an extra draw of the whole
    figure) for figures already laid out by ``tight_layout``.
    """
    path = Path(path)
    fmt = path.suffix.lstrip(".") or "png"
    extra = {"pil_kwargs": {"compress_level": 1}} if fmt == "png" else {}  # fast zlib: 3x faster, ~1.3x bigger
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight" if tight else None, format=fmt, **extra)
    _pyplot().close(fig)
    return path


def _exposure(image: np.ndarray, mask: Optional[np.ndarray] = None) -> float:
    if mask is not None and mask.shape != image.shape[:2]:     # e.g. input and novel renders differ in size
        mask = np.any(image > 0, axis=-1)
    values = image[mask] if mask is not None else image.reshape(-1, 3)
    lum = values @ np.array([0.2126, 0.7152, 0.0722])
    lum = lum[np.isfinite(lum) & (lum > 0)]
    level = np.percentile(lum, 99.0) if lum.size else 1.0
    return 1.0 / level if level > 0 else 1.0


def _show(ax: Any, image: np.ndarray, title: str, exposure: float) -> None:
    ax.imshow(tonemap(image, exposure))
    ax.set_title(title, fontsize=9)
    ax.set_axis_off()


def _difference(ax: Any, image: np.ndarray, reference: np.ndarray, mask: np.ndarray, title: str,
                scale: float = 100.0) -> None:
    """|image - reference| x scale, relative to the reference's mean (the paper shows x100)."""
    mean = float(np.mean(reference[mask])) if mask.any() else 1.0
    diff = np.abs(image - reference).mean(axis=2) / max(mean, 1e-30) * scale
    diff = np.where(mask, diff, np.nan)
    im = ax.imshow(diff, cmap="magma", vmin=0.0, vmax=max(1.0, np.nanpercentile(diff, 99)))
    ax.set_title(title, fontsize=9)
    ax.set_axis_off()
    ax.figure.colorbar(im, ax=ax, fraction=0.046, pad=0.02)


def plot_table(ax: Any, brdf: BivariateBRDF, title: str, channel: Optional[int] = None,
               vmin: Optional[float] = None, vmax: Optional[float] = None) -> Any:
    """log10 of a bivariate table over the st plane (x: s ~ theta_d, y: t ~ theta_h, specular at the bottom)."""
    table = brdf.table.mean(axis=2) if channel is None else brdf.table[..., channel]
    logt = np.log10(np.maximum(table, 1e-4))
    im = ax.imshow(logt, origin="lower", extent=(0, 1, 0, 1), cmap="viridis", vmin=vmin, vmax=vmax,
                   aspect="auto")
    ticks = np.array([0, 15, 30, 45, 60, 75, 90])
    ax.set_xticks(ticks / 90.0, [f"{t}" for t in ticks], fontsize=7)
    t_ticks = np.array([0, 1, 5, 15, 30, 60, 90])
    ax.set_yticks(np.sqrt(t_ticks / 90.0), [f"{t}" for t in t_ticks], fontsize=7)
    ax.set_xlabel("theta_d (deg)", fontsize=8)
    ax.set_ylabel("theta_h (deg)", fontsize=8)
    ax.set_title(title, fontsize=9)
    ax.figure.colorbar(im, ax=ax, fraction=0.046, pad=0.02, label="log10 f (1/sr)")
    return im


def incident_plane(theta_view_deg: float = 45.0, n: int = 181):
    """Angles of the incident plane for a fixed view: light from -90 to 90 degrees.

    Returns ``(theta_in_deg (n,), theta_h, theta_d, phi_d)`` with negative
    angles on the far side of the normal (the specular direction is at
    ``-theta_view``).
    """
    theta_in = np.linspace(-89.5, 89.5, n)
    ti = np.radians(theta_in)
    to = np.radians(theta_view_deg)
    wi = np.stack([np.sin(ti), np.zeros_like(ti), np.cos(ti)], axis=-1)
    wo = np.broadcast_to(np.array([np.sin(to), 0.0, np.cos(to)]), wi.shape)
    theta_h, _, theta_d, phi_d = half_diff_from_dirs(wi, wo)
    return theta_in, theta_h, theta_d, phi_d


def plot_incident_plane(ax: Any, curves: Dict[str, Any], theta_view_deg: float = 45.0, channel: int = 0) -> None:
    """Fig. 6 style: BRDF along the incident plane for one view angle (one channel, log scale).

    ``curves`` maps a label to an object with ``eval(theta_h, theta_d)`` (bivariate)
    or ``eval(theta_h, theta_d, phi_d)`` (3D).
    """
    theta_in, theta_h, theta_d, phi_d = incident_plane(theta_view_deg)
    styles = ["-", "--", "-", ":"]
    for k, (label, brdf) in enumerate(curves.items()):
        if isinstance(brdf, BivariateBRDF):
            values = brdf.eval(theta_h, theta_d)
        else:
            values = brdf.eval(theta_h, theta_d, phi_d, interpolation="linear")
        ax.plot(theta_in, values[..., channel], styles[k % len(styles)], label=label, lw=1.2)
    ax.set_yscale("log")
    ax.set_xlabel(f"light angle in the incident plane (deg), view at {theta_view_deg:g} deg", fontsize=8)
    ax.set_ylabel(f"f ({'RGB'[channel]}, 1/sr)", fontsize=8)
    ax.legend(fontsize=7)
    ax.grid(True, which="both", alpha=0.3)


def predicted_image(result: Any, index: int = 0) -> Tuple[Optional[np.ndarray], Optional[np.ndarray]]:
    """The model's own re-render: ``L f`` at the observed pixels of image ``index``, nearest-filled.

    The recovered table predicts each observation as a row of the lighting
    matrix times the table (``result.predicted``, ``(M, 3)``): a noise-free
    re-render at the observed normals at no extra cost. For display every
    sphere pixel takes the value of the nearest observed pixel (the lattice
    of observations is dense and even); the observations are filled the same
    way, so the difference of the two is exactly the fit residual at the
    observed pixels.

    Returns:
        ``(predicted, observed)``, ``(H, W, 3) float32`` each, zero off the
        sphere; ``(None, None)`` when the rows carry no pixel positions.
    """
    from scipy.spatial import cKDTree

    obs = result.observations
    image = result.images[index]
    rows = np.flatnonzero((np.asarray(obs.image_index) == index) & (np.asarray(obs.pixels)[:, 0] >= 0))
    if len(rows) == 0 or not result.geometries:
        return None, None
    _, mask = result.geometries[index].normals(image.shape[1], image.shape[0])
    target = np.argwhere(mask)
    _, nearest = cKDTree(np.asarray(obs.pixels)[rows]).query(target, k=1)
    predicted = np.zeros(image.shape[:2] + (3,), np.float32)
    observed = np.zeros_like(predicted)
    predicted[target[:, 0], target[:, 1]] = np.asarray(result.predicted)[rows[nearest]]
    observed[target[:, 0], target[:, 1]] = np.asarray(obs.values)[rows[nearest]]
    return predicted, observed


def write_recovery_report(result: Any, path: PathLike, rerender: Optional[np.ndarray] = None,
                          path_trace: bool = False) -> Path:
    """PNG report of a :class:`~mi_bivariate.recover.Recovery`.

    Panels: input image, a re-render of the recovered BRDF under the input
    probe and the difference, recovered table, per-node confidence (which
    nodes the image measured, which the priors supplied), model prediction
    ``L f`` against the observations.

    The re-render is ``rerender`` when given; else, with ``path_trace``, a
    Mitsuba path-traced render (128 spp, seconds); else (default) the model's
    own prediction ``L f`` at the observed normals (:func:`predicted_image`,
    milliseconds), compared with the observations at the same pixels.
    """
    plt = _pyplot()
    obs = result.observations
    image = result.images[0] if result.images else None
    reference = image
    label = "recovered BRDF re-rendered (same probe)"
    if rerender is None and image is not None and result.geometries:
        if path_trace:

            geo = result.geometries[0]
            rerender = render.render_like(render.bsdf_dict(result.brdf), result.probes[0], geo,
                                          width=image.shape[1], height=image.shape[0], spp=128, seed=1).image
        else:
            rerender, observed = predicted_image(result)
            if rerender is not None:
                reference = observed
                label = "prediction L f at the observed normals (nearest fill)"
    fig, axes = plt.subplots(2, 3, figsize=(13, 8))
    if image is not None:
        geo = result.geometries[0]
        normals, mask = geo.normals(image.shape[1], image.shape[0])
        exposure = _exposure(image, mask)
        _show(axes[0, 0], image, "input", exposure)
        if rerender is not None:
            _show(axes[0, 1], rerender, label, exposure)
            _difference(axes[0, 2], rerender, reference, mask, "|difference| x100 / mean")
    for ax in axes[0]:
        if not ax.images:
            ax.set_axis_off()
    plot_table(axes[1, 0], result.brdf, "recovered table (mean RGB)")
    # Which nodes the photo measured and which the priors supplied: how much of each node's
    # uncertainty under the priors alone the image removed (1: all, 0: none), worst channel.
    confidence = np.min(np.asarray(result.solution.measured), axis=-1)
    im = axes[1, 1].imshow(confidence, origin="lower", extent=(0, 1, 0, 1), cmap="magma", vmin=0.0, vmax=1.0,
                           aspect="auto")
    axes[1, 1].contour(np.linspace(0, 1, confidence.shape[1]), np.linspace(0, 1, confidence.shape[0]),
                       confidence, levels=[0.5], colors="w", linewidths=0.8)
    axes[1, 1].set_title(f"measured by the image (1) or supplied by the priors (0)\n"
                         f"{100 * float(np.mean(confidence > 0.5)):.0f}% of the nodes > 0.5 (white line)",
                         fontsize=9)
    axes[1, 1].set_xlabel("s = 2 theta_d / pi", fontsize=8)
    axes[1, 1].set_ylabel("t = sqrt(2 theta_h / pi)", fontsize=8)
    fig.colorbar(im, ax=axes[1, 1], fraction=0.046, pad=0.02)
    lum = np.array([0.2126, 0.7152, 0.0722])
    # log10 values on linear axes: the same picture as log axes without their
    # mathtext tick labels (the slowest part of drawing this figure).
    seen = np.log10(np.maximum(obs.values @ lum, 1e-6))
    fit = np.log10(np.maximum(result.predicted @ lum, 1e-6))
    axes[1, 2].plot(seen, fit, ".", ms=1.5, alpha=0.5)
    lo, hi = float(np.min(seen)), float(np.max(seen))
    axes[1, 2].plot([lo, hi], [lo, hi], "k-", lw=0.8)
    axes[1, 2].set_xlabel("log10 observed pixel (luminance)", fontsize=8)
    axes[1, 2].set_ylabel("log10 predicted L f", fontsize=8)
    axes[1, 2].set_title(f"fit: relative residual {result.relative_residual():.4f}", fontsize=9)
    fig.suptitle(result.adequacy.summary(), fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path, tight=False)


def write_demo_figure(path: PathLike, shot: Any, novel_rec: Any, novel_truth: Any, rec: Any, truth: Any,
                      floor: BivariateBRDF, numbers: Dict[str, Any]) -> Path:
    """The demo's figure (Fig. 5 + Fig. 6 analogue for one material)."""
    plt = _pyplot()
    fig, axes = plt.subplots(2, 4, figsize=(17, 8))
    _show(axes[0, 0], shot.image, f"input: {numbers['input_probe']}", _exposure(shot.image, shot.mask))
    exposure = _exposure(novel_truth.image, novel_truth.mask)
    _show(axes[0, 1], novel_rec.image, f"recovered, novel probe {numbers['novel_probe']}", exposure)
    _show(axes[0, 2], novel_truth.image, "ground truth (3D table)", exposure)
    _difference(axes[0, 3], novel_rec.image, novel_truth.image, novel_truth.mask,
                f"|difference| x100 / mean (rel. RMSE {numbers['image_relative_rmse_novel']:.3f})")
    lo = float(np.log10(max(np.percentile(floor.table, 1), 1e-4)))
    hi = float(np.log10(max(floor.table.max(), 1e-3)))
    plot_table(axes[1, 0], rec.brdf, f"recovered (Eq. 1 error {numbers['brdf_error_recovered_eq1']:.3f})",
               vmin=lo, vmax=hi)
    plot_table(axes[1, 1], floor, f"bivariate truth (floor {numbers['brdf_error_bivariate_floor_eq1']:.3f})",
               vmin=lo, vmax=hi)
    plot_incident_plane(axes[1, 2], {"3D truth": truth, "bivariate truth": floor, "recovered": rec.brdf},
                        theta_view_deg=30.0)
    plot_incident_plane(axes[1, 3], {"3D truth": truth, "bivariate truth": floor, "recovered": rec.brdf},
                        theta_view_deg=60.0)
    fig.suptitle(f"{numbers['material']}: recovered from one image", fontsize=11)
    fig.tight_layout()
    return save_figure(fig, path)


# ---------------------------------------------------------------------------
# Evaluation figures (mi_bivariate.evaluate): each takes the JSON records of
# results.jsonl and/or one material's artifact arrays (materials/<slug>.npz),
# returns a matplotlib figure, and never renders or recovers anything.

def close_figure(fig: Any) -> None:
    """Close a figure made by the functions below (after saving it in every format)."""
    _pyplot().close(fig)


def save_figure_formats(fig: Any, stem: PathLike, formats: Sequence[str] = ("png",), dpi: int = 100) -> list:
    """Save one figure as ``stem.<fmt>`` for every format (atomic), then close it."""
    stem = Path(stem)
    paths = []
    for fmt in formats:
        path = stem.with_name(f"{stem.name}.{fmt}")
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=dpi, bbox_inches="tight", format=fmt)
        paths.append(path)
    close_figure(fig)
    return paths


def _f32(image: np.ndarray) -> np.ndarray:
    return np.asarray(image, np.float32)


def _material_order(records: Sequence[dict], key: Any) -> list:
    return sorted(records, key=key)


_METRIC_LABELS = {"eq1": "Eq. 1 relative RMS", "eq1_min": "Eq. 1, cells f > 1e-3 1/sr",
                  "cosine": "cosine-weighted relative L2", "log": "RMS of ln(1 + f) difference"}


def plot_reduction_ranking(records: Sequence[dict], artifacts: Dict[str, Dict[str, np.ndarray]],
                           novel: str, metric: str = "eq1") -> Any:
    """Fig. 3 analogue: materials sorted by the error of their bivariate reduction (the floor).

    Top: the floor's errors per material (``metric`` sorts; all four metrics
    drawn, log scale). Bottom: the best and the worst material rendered under
    the probe ``novel`` with the full 3D BRDF and with its bivariate reduction.
    """
    plt = _pyplot()
    order = _material_order(records, lambda r: r["floor"][metric])
    fig = plt.figure(figsize=(12, 7.5))
    ax = fig.add_subplot(2, 1, 1)
    x = np.arange(len(order))
    for m, style in zip(("eq1", "eq1_min", "cosine", "log"), ("o-", "s--", "^-", "d:")):
        ax.semilogy(x, [max(r["floor"][m], 1e-6) for r in order], style, ms=4, lw=1, label=_METRIC_LABELS[m])
    ax.set_xticks(x, [r["material"] for r in order], rotation=60, ha="right", fontsize=7)
    ax.set_ylabel("error of the bivariate reduction", fontsize=8)
    ax.set_title(f"bivariate reduction (Eq. 1 projection) of each material, sorted by {_METRIC_LABELS[metric]}",
                 fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    for k, (r, tag) in enumerate(((order[0], "best"), (order[-1], "worst"))):
        art = artifacts[r["material"]]
        truth, floor, mask = _f32(art[f"truth__{novel}"]), _f32(art[f"floor_render__{novel}"]), art["mask"]
        exposure = _exposure(truth, mask)
        _show(fig.add_subplot(2, 4, 5 + 2 * k), truth, f"{tag}: {r['material']}\n3D truth ({novel})", exposure)
        _show(fig.add_subplot(2, 4, 6 + 2 * k), floor,
              f"bivariate reduction\n(Eq. 1 {r['floor']['eq1']:.3g}, log {r['floor']['log']:.3g})", exposure)
    fig.tight_layout()
    return fig


def plot_validation(record: dict, art: Dict[str, np.ndarray], input_probe: str, novel: str) -> Any:
    """Fig. 5 analogue: input image, recovered re-render, ground truth, |difference| x100 under ``novel``."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 4, figsize=(15, 3.9))
    mask = art["mask"]
    image = _f32(art[f"input__{input_probe}"])
    _show(axes[0], image, f"input: {record['material']}\nunder {input_probe}", _exposure(image, mask))
    truth = _f32(art[f"truth__{novel}"])
    rec = _f32(art[f"recovered_render__{input_probe}__{novel}"])
    exposure = _exposure(truth, mask)
    errs = record["inputs"][input_probe]["images"][novel]
    _show(axes[1], rec, f"recovered, novel probe {novel}", exposure)
    _show(axes[2], truth, "ground truth (3D table)", exposure)
    _difference(axes[3], rec, truth, mask,
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
    plt = _pyplot()
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
    plt = _pyplot()
    probes = list(records[0]["inputs"])
    fig, axes = plt.subplots(1, len(metrics), figsize=(6 * len(metrics), 4.2), squeeze=False)
    for ax, m in zip(axes[0], metrics):
        order = _material_order(records, lambda r: r["floor"][m])
        x = np.arange(len(order))
        ax.fill_between(x, 1e-6, [max(r["floor"][m], 1e-6) for r in order], color="0.85", label="floor (bivariate truth)")
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
    im = ax.imshow(np.log10(np.maximum(omap, 1e-3)), origin="lower", extent=(0, 1, 0, 1), cmap="cividis",
                   aspect="auto")
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("s = 2 theta_d / pi", fontsize=8)
    ax.set_ylabel("t = sqrt(2 theta_h / pi)", fontsize=8)
    ax.figure.colorbar(im, ax=ax, fraction=0.046, pad=0.02, label="log10 observations")


def plot_environment_dependence(record: dict, art: Dict[str, np.ndarray], input_probes: Sequence[str]) -> Any:
    """Fig. 7 analogue: one material recovered under each input probe, with the adequacy map.

    Row per input probe: input image, st observation map (adequacy), recovered
    table, bivariate truth, re-render under the first novel probe.
    """
    plt = _pyplot()
    novel = sorted(k.split("__")[1] for k in art if k.startswith("truth__"))[0]
    floor = BivariateBRDF(np.asarray(art["floor"], np.float32))
    lo = float(np.log10(max(np.percentile(floor.table, 1), 1e-4)))
    hi = float(np.log10(max(floor.table.max(), 1e-3)))
    fig, axes = plt.subplots(len(input_probes), 5, figsize=(22, 4 * len(input_probes)), squeeze=False)
    mask = art["mask"]
    for row, p in zip(axes, input_probes):
        e = record["inputs"][p]
        a = e["adequacy"]
        image = _f32(art[f"input__{p}"])
        _show(row[0], image, f"input under {p}", _exposure(image, mask))
        _observation_image(row[1], art[f"observation_map__{p}"],
                           f"adequacy: rank {a['rank_fraction']:.2f}, cond {a['condition_number']:.2g}"
                           + ("" if a["adequate"] else " (flagged)"))
        r = e["recovered"]
        plot_table(row[2], BivariateBRDF(np.asarray(art[f"recovered__{p}"], np.float32)),
                   f"recovered (log err {r['log']:.3f}, Eq. 1 {r['eq1']:.3g})", vmin=lo, vmax=hi)
        plot_table(row[3], floor, f"bivariate truth (log err {record['floor']['log']:.3f})", vmin=lo, vmax=hi)
        truth = _f32(art[f"truth__{novel}"])
        _show(row[4], _f32(art[f"recovered_render__{p}__{novel}"]),
              f"re-render under {novel} (rel. RMSE {e['images'][novel]['rel_rmse']:.3f})", _exposure(truth, mask))
    fig.suptitle(f"{record['material']}: the same material recovered under different environments", fontsize=11)
    fig.tight_layout()
    return fig


def plot_table_gallery(records: Sequence[dict], artifacts: Dict[str, Dict[str, np.ndarray]],
                       input_probes: Sequence[str], columns: int = 2) -> Any:
    """(theta_h, theta_d) images (log10 mean RGB) of every recovered table next to the bivariate truth.

    Per material: truth, then one panel per input probe, on a shared colour
    scale (x: theta_d, y: t ~ sqrt(theta_h), specular peak at the bottom).
    """
    plt = _pyplot()
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
            ax.imshow(np.log10(np.maximum(table, 1e-4)), origin="lower", extent=(0, 1, 0, 1), cmap="viridis",
                      vmin=lo, vmax=hi, aspect="auto")
            ax.set_title((r["material"][:22] + "\n" if j == 0 else "\n") + label, fontsize=6)
    fig.tight_layout()
    return fig


def plot_baselines(records: Sequence[dict], input_probe: str, metrics: Sequence[str] = ("log", "eq1_min")) -> Any:
    """Per-material errors of the bivariate recovery, the parametric baselines and the floor."""
    plt = _pyplot()
    families = list(records[0]["inputs"][input_probe].get("baselines", {}))
    fig, axes = plt.subplots(len(metrics), 1, figsize=(13, 3.6 * len(metrics)), squeeze=False)
    for ax, m in zip(axes[:, 0], metrics):
        order = _material_order(records, lambda r: r["inputs"][input_probe]["recovered"][m])
        x = np.arange(len(order))
        series = [("bivariate recovery", [r["inputs"][input_probe]["recovered"][m] for r in order])]
        series += [(f"{f} fit (3D)", [r["inputs"][input_probe]["baselines"][f]["errors"][m] for r in order])
                   for f in families]
        series.append(("bivariate floor", [r["floor"][m] for r in order]))
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
