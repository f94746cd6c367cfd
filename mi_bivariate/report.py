"""Figures: the recovery report (PNG) and the demo figure.

matplotlib with the non-interactive Agg backend; every file is written
atomically. Images are shown tonemapped with one exposure per row so that
recovered and reference renders are directly comparable.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Dict, Optional, Sequence, Union

import numpy as np

from mi_bivariate.atomic import atomic_path
from mi_bivariate.bivariate import BivariateBRDF
from mi_bivariate.coordinates import dirs_from_half_diff, half_diff_from_dirs
from mi_bivariate.images import tonemap

PathLike = Union[str, os.PathLike]


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, path: PathLike, dpi: int = 110) -> Path:
    """Save a matplotlib figure atomically (format from the suffix) and close it."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight", format=path.suffix.lstrip(".") or "png")
    _pyplot().close(fig)
    return path


def _exposure(image: np.ndarray, mask: Optional[np.ndarray] = None) -> float:
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


def write_recovery_report(result: Any, path: PathLike, rerender: Optional[np.ndarray] = None) -> Path:
    """PNG report of a :class:`~mi_bivariate.recover.Recovery`.

    Panels: input image with the used normals, model prediction ``L f`` at
    those normals against the observations, recovered table, st coverage
    (adequacy), a re-render of the recovered BRDF under the input probe and
    the difference (when ``rerender`` is given or can be rendered).
    """
    plt = _pyplot()
    obs = result.observations
    image = result.images[0] if result.images else None
    if rerender is None and image is not None and result.geometries:
        from mi_bivariate import render

        geo = result.geometries[0]
        rerender = render.render_like(render.bsdf_dict(result.brdf), result.probes[0], geo,
                                      width=image.shape[1], height=image.shape[0], spp=64, seed=1).image
    fig, axes = plt.subplots(2, 3, figsize=(13, 8))
    if image is not None:
        geo = result.geometries[0]
        normals, mask = geo.normals(image.shape[1], image.shape[0])
        exposure = _exposure(image, mask)
        _show(axes[0, 0], image, "input", exposure)
        if obs.pixels is not None:
            sel = obs.image_index == 0 if obs.image_index is not None else slice(None)
            px = obs.pixels[sel]
            axes[0, 0].plot(px[:, 1] + 0.5, px[:, 0] + 0.5, ",", color="cyan", alpha=0.4)
        if rerender is not None:
            _show(axes[0, 1], rerender, "recovered BRDF re-rendered (same probe)", exposure)
            _difference(axes[0, 2], rerender, image, mask, "|difference| x100 / mean")
    for ax in axes[0]:
        if not ax.images:
            ax.set_axis_off()
    plot_table(axes[1, 0], result.brdf, "recovered table (mean RGB)")
    coverage = np.asarray(result.adequacy.observation_map)
    im = axes[1, 1].imshow(np.log10(np.maximum(coverage / max(coverage.max(), 1e-30), 1e-6)), origin="lower",
                           extent=(0, 1, 0, 1), cmap="cividis", aspect="auto")
    axes[1, 1].set_title("st coverage (log10 relative weight)", fontsize=9)
    axes[1, 1].set_xlabel("s = 2 theta_d / pi", fontsize=8)
    axes[1, 1].set_ylabel("t = sqrt(2 theta_h / pi)", fontsize=8)
    fig.colorbar(im, ax=axes[1, 1], fraction=0.046, pad=0.02)
    lum = np.array([0.2126, 0.7152, 0.0722])
    axes[1, 2].loglog(obs.values @ lum, result.predicted @ lum, ".", ms=1.5, alpha=0.5)
    lo = max(float(np.min(obs.values @ lum)), 1e-6)
    hi = float(np.max(obs.values @ lum))
    axes[1, 2].plot([lo, hi], [lo, hi], "k-", lw=0.8)
    axes[1, 2].set_xlabel("observed pixel (luminance)", fontsize=8)
    axes[1, 2].set_ylabel("predicted L f", fontsize=8)
    axes[1, 2].set_title(f"fit: relative residual {result.relative_residual():.4f}", fontsize=9)
    fig.suptitle(result.adequacy.summary(), fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path)


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
