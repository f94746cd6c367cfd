"""The GGX and Ward baselines' Eq. 1 with and without the two MERL nodes exactly on the horizon.

    MI_BIVARIATE_DATA=../shared/data OPENBLAS_NUM_THREADS=1 python benchmarks/baselines_horizon.py [MATERIALS]

Until commit dc21ff3 ("merl.above_horizon: a configuration exactly on the horizon is not above
it") the MERL nodes (theta_h, theta_d, phi_d) = (30, 80, 0) and (60, 50, 0), where
theta_h + theta_d = pi/2 and wi lies on the horizon, counted as above it (their height rounded to
+8e-17 and +1.1e-16) and were scored in Eq. 1. Ward's lobe has 1/sqrt(cos_i cos_o), ~1e8 1/sr
there; GGX's has no such factor. This measures, for the same fitted models, Eq. 1 with the fixed
mask (the cells ``metrics.BRDFErrors`` scores now) and with the old one (those two cells put
back, holding the NBRDF's value there, as the truth tables held them before the fix).

Row level (3000 normals of a 128 px sphere, clean input under grace_latlong_1k, K = 8000, the
32 x 32 grid; ``ablation.sphere_rows``, ``render_rows``, ``full_table``, as
``benchmarks/eq1_alpha.py``). The baselines are fitted as the evaluation fits them
(``evaluate.protocol.fit_baselines``: ``baselines.fit_baselines`` on the same lighting matrix and
rows, the evaluation's families and ``baseline_nfev``) and scored as it scores them
(``BRDFErrors(truth)(fit.brdf, observed_nodes=...)``, the observed nodes of
``adequacy.observed_nodes``): Eq. 1 over all cells, over f > 1e-3 1/sr and over the observed
cells. The fit itself does not depend on the fix: the 32 x 32 grid's phi_d samples
(``baselines.PhiAverager``) have no configuration on the horizon (checked below). A diagnostic: it
chooses nothing, and its rows are not the evaluation's rendered images, so its medians are not
the published ones.
"""

from __future__ import annotations

import argparse
import datetime
import time

import numpy as np
from _machine import machine  # benchmarks/_machine.py
from ablation import full_table, render_rows, sphere_rows

from mi_bivariate import adequacy, baselines, lighting, nbrdf
from mi_bivariate.bivariate import _ST_MAX
from mi_bivariate.coordinates import grid_nodes, half_diff_from_st
from mi_bivariate.evaluate.config import EvalConfig
from mi_bivariate.merl import MERLBRDF, above_horizon, geometric_mask, node_angles
from mi_bivariate.metrics import BRDFErrors
from mi_bivariate.threads import jit_threads
from mi_bivariate.variants import ensure_variant

#: The Eq. 1 variants scored (keys of ``BRDFErrors``'s result) and their labels.
METRICS = (("eq1", "Eq. 1 all cells"), ("eq1_min", "Eq. 1 f > 1e-3"), ("eq1_observed", "Eq. 1 observed"))


def old_geometric_mask() -> np.ndarray:
    """``(90, 90, 180) bool``: ``merl.geometric_mask`` before the fix."""
    theta_h, theta_d, phi_d = node_angles()
    return above_horizon(theta_h[:, None, None], theta_d[None, :, None], phi_d[None, None, :], height=0.0)


class OldHorizonMERL(MERLBRDF):
    """A MERL table whose valid cells are those of the old horizon test (finite in all channels)."""

    def valid_mask(self) -> np.ndarray:
        return np.all(np.isfinite(self.table), axis=-1) & old_geometric_mask()


def horizon_nodes() -> tuple:
    """Index arrays ``(i_h, i_d, i_p)`` of the nodes the old test kept and the fixed one drops."""
    nodes = np.nonzero(old_geometric_mask() & ~geometric_mask())
    found = sorted(zip(*(n.tolist() for n in nodes)))
    assert found == [(30, 80, 0), (60, 50, 0)], found
    return nodes


def fit_is_unchanged(grid) -> None:
    """The fit's phi_d samples (``PhiAverager``) are the same under the old and the fixed test."""
    n_t, n_s = grid
    averager = baselines.PhiAverager(n_t, n_s)
    theta_h, _ = half_diff_from_st(0.0, np.minimum(grid_nodes(n_t), _ST_MAX))
    _, theta_d = half_diff_from_st(np.minimum(grid_nodes(n_s), _ST_MAX), 0.0)
    phi_d = np.arange(averager.valid.shape[2]) * (np.pi / averager.valid.shape[2])
    old = above_horizon(theta_h[:, None, None], theta_d[None, :, None], phi_d[None, None, :], height=0.0)
    assert np.array_equal(old, averager.valid), "the fit's phi_d samples depend on the horizon test"


def old_truth(truth: MERLBRDF, full: np.ndarray, nodes) -> OldHorizonMERL:
    """The truth as it was tabulated before the fix: the NBRDF's values put back at ``nodes``."""
    valid = truth.valid_mask()
    # full_table and nbrdf.tabulate evaluate the same network on the same nodes.
    np.testing.assert_allclose(full[valid], truth.table[valid], rtol=1e-5, atol=1e-7)
    table = np.array(truth.table)
    table[nodes] = full[nodes]
    return OldHorizonMERL(table, name=truth.name + " (old horizon)")


def _rgb(values) -> str:
    """Compact text of a value, an RGB triple or a list of triples."""
    values = np.asarray(values, np.float64)
    if values.ndim == 0:
        return f"{values:.3g}"
    if values.ndim == 1:
        return "(" + " ".join(f"{v:.3g}" for v in values) + ")"
    return ", ".join(_rgb(v) for v in values)


def score(name: str, obs, grace, L, observed, cfg: EvalConfig, nodes) -> dict:
    """Both families' fit and Eq. 1 (fixed and old mask) on one material; prints its table."""
    t0 = time.perf_counter()
    full = full_table(name)
    with jit_threads(1):  # render_rows' scatter-adds sum in the threads' order; Ward's fit amplifies the bits
        I = render_rows(obs, grace, full)
    truth = nbrdf.nbrdf_merl(name)
    fits = baselines.fit_baselines(L, I, grid=cfg.grid, families=cfg.baselines, max_nfev=cfg.baseline_nfev)
    new, old = BRDFErrors(truth), BRDFErrors(old_truth(truth, full, nodes))
    th, td, pd = (a[n] for a, n in zip(node_angles(), nodes))
    out = {}
    lines = [f"{name}: truth at the two nodes {_rgb(full[nodes])} 1/sr"]
    for fam, fit in fits.items():
        e_new, e_old = new(fit.brdf, observed_nodes=observed), old(fit.brdf, observed_nodes=observed)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            at = np.asarray(fit.brdf.eval(th, td, pd))
        out[fam] = {key: (e_new[key], e_old[key]) for key, _ in METRICS}
        params = ", ".join(f"{k} {_rgb(v)}" for k, v in fit.params.items())
        lines.append(f"  {fam:4s} ({params}; model at the two nodes {_rgb(at)} 1/sr)")
        lines.extend(f"    {label:16s} fixed {e_new[key]:10.4g}   old {e_old[key]:10.4g}" for key, label in METRICS)
    print("\n".join(lines) + f"\n  ({time.perf_counter() - t0:.0f} s)", flush=True)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("materials", nargs="?", default=",".join(nbrdf.NBRDF_MATERIALS),
                        help="comma-separated MERL-NBRDF names (default: the 23 development materials)")
    args = parser.parse_args()
    names = args.materials.split(",")
    print(f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC; {machine()}", flush=True)
    ensure_variant()
    cfg = EvalConfig()
    nodes = horizon_nodes()
    fit_is_unchanged(cfg.grid)
    obs, grace = sphere_rows(3000)
    L = lighting.lighting_matrix(obs, grace, n_dirs=8000)
    observed = adequacy.observed_nodes(L, *cfg.grid)
    results = {name: score(name, obs, grace, L, observed, cfg, nodes) for name in names}
    print(f"\nMedians over {len(names)} materials (fixed mask / old mask, the two horizon nodes in):")
    for fam in cfg.baselines:
        cells = [f"{label} {np.median([r[fam][key][0] for r in results.values()]):.4g} / "
                 f"{np.median([r[fam][key][1] for r in results.values()]):.4g}" for key, label in METRICS]
        print(f"  {fam:4s}: " + "; ".join(cells))


if __name__ == "__main__":
    main()
