"""Do the recovered tables' zero nodes explain Eq. 1? (a diagnostic of an evaluation's saved tables)

    MI_BIVARIATE_DATA=../shared/data python benchmarks/eq1_zero_nodes.py out/eval_s24 [--input grace_latlong_1k]

The non-negative solve clamps some nodes of some channels to 0 (dark spots in the report's table
panel) where the truth is well above 0. Eq. 1 is a relative error, so a zero node counts 100%
there. This rescores each saved recovered table (the evaluation's ``materials/<config>/<material>.npz``)
with its zero entries (below 1e-7 of the table's largest) replaced by the grid floor's (the
exact phi_d average at the nodes: a repair that knows the truth, though not an upper bound, since
the neighbouring nodes were fitted around the zeros) and by the geometric mean of their non-zero
neighbours (a repair that needs no truth), and prints Eq. 1 over the observed cells and over
f > 1e-3 for each, against the exact floor's over the same cells.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from mi_bivariate import nbrdf
from mi_bivariate.bivariate import BivariateBRDF, phi_d_average
from mi_bivariate.metrics import BRDFErrors


def neighbour_fill(table: np.ndarray, zero: np.ndarray, rounds: int = 32) -> np.ndarray:
    """``table`` with its ``zero`` entries set to the geometric mean of their non-zero 4-neighbours
    (per channel; repeated so that holes fill from their edges)."""
    out, todo = table.copy(), zero.copy()
    for _ in range(rounds):
        if not todo.any():
            break
        log = np.where(todo, np.nan, np.log(np.maximum(out, 1e-30)))
        pad = np.pad(log, ((1, 1), (1, 1), (0, 0)), constant_values=np.nan)
        near = np.stack([pad[:-2, 1:-1], pad[2:, 1:-1], pad[1:-1, :-2], pad[1:-1, 2:]])
        count = np.sum(np.isfinite(near), axis=0)
        mean = np.where(count > 0, np.nansum(near, axis=0) / np.maximum(count, 1), np.nan)
        fill = todo & np.isfinite(mean)
        out[fill] = np.exp(mean[fill])
        todo &= ~fill
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("evaluation", type=Path, help="an `mi-bivariate evaluate` output folder")
    parser.add_argument("--input", default="grace_latlong_1k", help="the input probe(s) whose tables to rescore")
    args = parser.parse_args()
    files = sorted(args.evaluation.glob("materials/*/*.npz"))
    if not files:
        raise SystemExit(f"{args.evaluation}: no materials/*/*.npz (run `mi-bivariate evaluate` first)")
    print("| material | zero entries (nodes) | exact floor: observed / f > 1e-3 | recovered | zeros from the "
          "floor | zeros from their neighbours |")
    print("|---|---:|---|---|---|---|")
    ratios = []
    for path in files:
        saved = np.load(path)
        key = f"recovered__{args.input}"
        if key not in saved.files:
            continue
        table = saved[key].astype(np.float64)
        floor_table, observed = saved["floor"].astype(np.float64), saved[f"observed_nodes__{args.input}"]
        truth = nbrdf.nbrdf_merl(path.stem)
        errors = BRDFErrors(truth)
        zero = table <= 1e-7 * table.max()
        exact = errors(phi_d_average(truth), observed)  # the exact phi_d average at the MERL nodes
        cells = [f"{exact['eq1_observed']:.3f} / {exact['eq1_min']:.3f}"]
        row = []
        for variant in (table, np.where(zero, floor_table, table), neighbour_fill(table, zero)):
            e = errors(BivariateBRDF(variant.astype(np.float32)), observed)
            cells.append(f"{e['eq1_observed']:.3f} / {e['eq1_min']:.3f}")
            row.append((e["eq1_observed"] / exact["eq1_observed"], e["eq1_min"] / exact["eq1_min"]))
        ratios.append(row)
        print(f"| {path.stem} | {int(zero.sum())} ({int(zero.any(-1).sum())}) | " + " | ".join(cells) + " |",
              flush=True)
    med = np.median(np.array(ratios), axis=0)
    print(f"\nMedian over {len(ratios)} materials of Eq. 1 / the exact floor (observed cells, f > 1e-3): "
          + "; ".join(f"{name} {a:.2f}, {b:.2f}" for name, (a, b) in
                      zip(("recovered", "zeros from the floor", "zeros from their neighbours"), med)))


if __name__ == "__main__":
    main()
