"""Do the recovered tables' zero nodes hurt relighting? (a diagnostic: it chooses nothing)

    MI_BIVARIATE_DATA=../shared/data OPENBLAS_NUM_THREADS=1 python benchmarks/zero_nodes_relight.py \\
        --materials tungsten-carbide,brass,specular-white-phenolic,red-phenolic,blue-acrylic

The non-negative solve clamps some entries of a recovered table to 0 (dark spots in the report's
table panel). ``eq1_zero_nodes.py`` found that they are not Eq. 1's gap; this asks whether they
cost relighting. By the row-level protocol of ``benchmarks/ablation.py`` (1000 normals of a
128 px sphere, clean input under grace_latlong_1k, relit under grace_256 / pisa_256 /
pedestrian_overpass_1k as ``L_novel f``, leave-one-out priors, ``recover``'s solve at 32 x 32) it
prints, per material, the median relight error of the recovered table as solved, with its zero
entries (below 1e-7 of its largest) set to the nearest non-zero node's value of the same channel
(a repair without the truth), and set to the exact reduction's values there (a repair that knows
the truth); and the relative residual of each against the input rows.
"""

from __future__ import annotations

import argparse

import numpy as np
from ablation import NOVEL, full_table, rel, render_rows, sphere_rows  # benchmarks/ablation.py
from eq1_zero_nodes import nearest_fill  # benchmarks/eq1_zero_nodes.py

from mi_bivariate import lighting, probes, solve, training_set
from mi_bivariate.solve import solve_stages
from mi_bivariate.variants import ensure_variant

GRID = (32, 32)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--materials", default="tungsten-carbide,brass,specular-white-phenolic,red-phenolic,"
                                               "blue-acrylic,white-paint,pink-jasper")
    parser.add_argument("--normals", type=int, default=1000)
    args = parser.parse_args()
    ensure_variant()
    n_t, n_s = GRID
    obs, grace = sphere_rows(args.normals)
    novel = {p: probes.shared_probe(p) for p in NOVEL}
    L_in = lighting.lighting_matrix(obs, grace, n_t=n_t, n_s=n_s, n_dirs=32768)
    L_novel = {p: lighting.lighting_matrix(obs, novel[p], n_t=n_t, n_s=n_s, n_dirs=32768, seed=5) for p in NOVEL}
    reduced = training_set.reduced_tables(n_t, n_s)

    def relight(table: np.ndarray, truth: dict) -> float:
        return float(np.median([rel(np.einsum("mnc,nc->mc", L_novel[p], table.reshape(-1, 3)), truth[p])
                                for p in NOVEL]))

    def residual(table: np.ndarray, pixels: np.ndarray) -> float:
        return rel(np.einsum("mnc,nc->mc", L_in, table.reshape(-1, 3)), pixels)

    print("| material | zero entries | relight: as solved | zeros from the nearest node | zeros from the truth "
          "| exact reduction (floor) | input residual: as solved / nearest node |")
    print("|---|---:|---:|---:|---:|---:|---|")
    for name in args.materials.split(","):
        table3d = full_table(name)
        pixels = render_rows(obs, grace, table3d)
        truth = {p: render_rows(obs, novel[p], table3d) for p in NOVEL}
        prior, basis = training_set.learn_priors(reduced, exclude=(name,))
        data = solve.prepare_data_term(L_in, pixels, solve.row_sigma(pixels))
        table = solve_stages(data, prior, "discrepancy", basis, "evidence").table.reshape(n_t, n_s, 3)
        zero = table <= 1e-7 * table.max()
        nearest = nearest_fill(table, zero)
        exact = reduced[name].reshape(n_t, n_s, 3)
        repaired = np.where(zero, exact, table)
        print(f"| {name} | {int(zero.sum())} | {relight(table, truth):.4f} | {relight(nearest, truth):.4f} | "
              f"{relight(repaired, truth):.4f} | {relight(exact, truth):.4f} | "
              f"{residual(table, pixels):.4f} / {residual(nearest, pixels):.4f} |", flush=True)


if __name__ == "__main__":
    main()
