"""Eq. 1 on observed cells against alpha: how close a table fitted to one image can come to the exact reduction.

    MI_BIVARIATE_DATA=../shared/data OPENBLAS_NUM_THREADS=1 python benchmarks/eq1_alpha.py \
        alum-bronze,black-fabric,red-phenolic,white-paint 1,0.1,1e-2,1e-4,1e-6,1e-8

Row level (3000 normals of a 128 px sphere, clean input under grace_latlong_1k, K = 8000, the
32 x 32 grid, leave-one-out priors). For each alpha, the smoothness prior alone (stage 1, pair
kept by the evidence); then the default solve (``solve.solve_stages``: discrepancy alpha and
basis prior). Eq. 1 over the cells of the observed nodes (``adequacy.observed_nodes``) against
the 3D truth, and its ratio to the exact floor, Eq. 1 of the phi_d average over all cells (the
ratio issue 9 scores; the 32 x 32 table's own floor, the grid floor, is printed beside it). A
diagnostic for development materials: it chooses nothing.

Before 2026-12-06 the ratio's denominator was the grid floor, labelled "exact floor" (an audit
found it); ``docs/recovery.md`` section 4d gives both.
"""

from __future__ import annotations

import argparse

from ablation import full_table, render_rows, sphere_rows

from mi_bivariate import adequacy, lighting, nbrdf, solve, training_set
from mi_bivariate.bivariate import BivariateBRDF, phi_d_average
from mi_bivariate.metrics import BRDFErrors
from mi_bivariate.solve import solve_stages
from mi_bivariate.variants import ensure_variant


def row_setup():
    """``(obs, grace, L, observed, tables)``: 3000 normals, their K = 8000 lighting matrix under
    grace_latlong_1k, its observed nodes and the exact reductions of the shared materials."""
    obs, grace = sphere_rows(3000)
    L = lighting.lighting_matrix(obs, grace, n_dirs=8000)
    return obs, grace, L, adequacy.observed_nodes(L, 32, 32), training_set.reduced_tables(32, 32)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("materials", help="comma-separated MERL-NBRDF names")
    parser.add_argument("alphas", help="comma-separated alphas")
    args = parser.parse_args()
    names, alphas = args.materials.split(","), [float(a) for a in args.alphas.split(",")]
    ensure_variant()
    obs, grace, L, observed, tables = row_setup()
    for name in names:
        truth = nbrdf.nbrdf_merl(name)
        errors = BRDFErrors(truth)
        exact = errors(phi_d_average(truth), observed_nodes=observed)["eq1"]  # the exact floor (paper Fig. 3)
        grid = errors(BivariateBRDF(tables[name]), observed_nodes=observed)
        prior, basis = training_set.learn_priors(tables, exclude=(name,))
        data = solve.prepare_data_term(L, render_rows(obs, grace, full_table(name)))
        cells = [f"{name}: exact floor {exact:.3f}, grid floor {grid['eq1']:.3f} (observed cells "
                 f"{grid['eq1_observed']:.3f}); Eq. 1 observed (/ exact floor, / grid floor)"]
        for alpha in alphas:
            e = errors(BivariateBRDF(solve.solve_prepared(data, prior, alpha).table), observed_nodes=observed)
            cells.append(f"alpha {alpha:.0e}: {e['eq1_observed']:.3f} ({e['eq1_observed'] / exact:.2f}x, "
                         f"{e['eq1_observed'] / grid['eq1']:.2f}x)")
        e = errors(BivariateBRDF(solve_stages(data, prior, None, basis).table), observed_nodes=observed)
        cells.append(f"default: {e['eq1_observed']:.3f} ({e['eq1_observed'] / exact:.2f}x, "
                     f"{e['eq1_observed'] / grid['eq1']:.2f}x)")
        print(" | ".join(cells), flush=True)


if __name__ == "__main__":
    main()
