"""Do the recovered tables' zero nodes explain Eq. 1? (a diagnostic of an evaluation's saved tables)

    MI_BIVARIATE_DATA=../shared/data python benchmarks/eq1_zero_nodes.py out/eval_s24 [--input grace_latlong_1k]

The non-negative solve clamps some nodes of some channels to 0 (dark spots in the report's table
panel) where the truth is well above 0. Eq. 1 is a relative error, so a zero node counts 100%
there. This rescores each saved recovered table (the artifacts of the folder's recorded materials,
``evaluate.artifact_path``) with its zero entries (below 1e-7 of the table's largest) replaced by
the grid floor's (the exact phi_d average at the nodes: a repair that knows the truth, though not
an upper bound, since the neighbouring nodes were fitted around the zeros) and by the value of
the nearest non-zero node of the same channel (a repair that needs no truth), and prints Eq. 1
over the observed cells and over f > 1e-3 for each, against the exact floor's over the same cells.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.ndimage import distance_transform_edt

from mi_bivariate import evaluate as ev
from mi_bivariate.bivariate import BivariateBRDF, phi_d_average
from mi_bivariate.metrics import BRDFErrors


def nearest_fill(table: np.ndarray, zero: np.ndarray) -> np.ndarray:
    """``table`` ``(n_t, n_s, 3)`` with each ``zero`` entry set to the nearest non-zero node's value, per channel."""
    out = table.copy()
    for c in range(table.shape[2]):
        if zero[..., c].any() and not zero[..., c].all():
            _, (ii, jj) = distance_transform_edt(zero[..., c], return_indices=True)
            out[..., c] = table[ii, jj, c]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("evaluation", type=Path, help="an `mi-bivariate evaluate` output folder")
    parser.add_argument("--input", default="grace_latlong_1k", help="the input probe(s) whose tables to rescore")
    args = parser.parse_args()
    records = ev.read_records(args.evaluation / "results.jsonl")
    if not records:
        raise SystemExit(f"{args.evaluation}: no results.jsonl records (run `mi-bivariate evaluate` first)")
    print("| material | zero entries (nodes) | exact floor: observed / f > 1e-3 | recovered | zeros from the "
          "floor | zeros from the nearest node |")
    print("|---|---:|---|---|---|---|")
    ratios = []
    for record in records:
        saved = ev.load_artifacts(ev.artifact_path(args.evaluation, record))
        key = f"recovered__{args.input}"
        if key not in saved:
            continue
        table = saved[key].astype(np.float64)
        floor_table, observed = saved["floor"].astype(np.float64), saved[f"observed_nodes__{args.input}"]
        truth = ev.load_truth(ev.MaterialSpec(record["material"], record["kind"], record["spec"]))
        errors = BRDFErrors(truth)
        zero = table <= 1e-7 * table.max()
        exact = errors(phi_d_average(truth), observed)  # the exact phi_d average at the MERL nodes
        cells = [f"{exact['eq1_observed']:.3f} / {exact['eq1_min']:.3f}"]
        row = []
        for variant in (table, np.where(zero, floor_table, table), nearest_fill(table, zero)):
            e = errors(BivariateBRDF(variant.astype(np.float32)), observed)
            cells.append(f"{e['eq1_observed']:.3f} / {e['eq1_min']:.3f}")
            row.append((e["eq1_observed"] / exact["eq1_observed"], e["eq1_min"] / exact["eq1_min"]))
        ratios.append(row)
        print(f"| {record['material']} | {int(zero.sum())} ({int(zero.any(-1).sum())}) | " + " | ".join(cells)
              + " |", flush=True)
    med = np.median(np.array(ratios), axis=0)
    print(f"\nMedian over {len(ratios)} materials of Eq. 1 / the exact floor (observed cells, f > 1e-3): "
          + "; ".join(f"{name} {a:.2f}, {b:.2f}" for name, (a, b) in
                      zip(("recovered", "zeros from the floor", "zeros from the nearest node"), med)))


if __name__ == "__main__":
    main()
