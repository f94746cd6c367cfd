"""The exact floor is not a lower bound of Eq. 1: the per-node constant that minimises a relative error.

    MI_BIVARIATE_DATA=../shared/data python benchmarks/eq1_optimal.py [MATERIAL ...]

Eq. 1 scores a bivariate estimate ``c(theta_h, theta_d)`` by ``sqrt(mean ((c - f) / f)^2)`` over the
MERL cells (valid, f > 0). Per (theta_h, theta_d) node and channel, the constant that minimises
``sum_phi_d ((c - f) / f)^2`` is ``c* = sum(1/f) / sum(1/f^2)``, not the mean of ``f`` (the paper's
phi_d average, whose Eq. 1 is the *exact floor*, Fig. 3). The script prints, per material, the
exact floor (``bivariate.exact_floor``) and Eq. 1 of ``c*`` through the same metric
(``metrics.BRDFErrors``). It says what the floor is (the error of the paper's reduction, the one
that relighting needs: a render averages ``f`` linearly over phi_d) and what it is not.
docs/results.md ("BRDF errors") and ``bivariate.exact_floor`` quote its figures.
"""

from __future__ import annotations

import argparse

import numpy as np

from mi_bivariate import bivariate, metrics, nbrdf

MATERIALS = ("gold-metallic-paint3", "red-phenolic", "white-paint")


def eq1_optimal_constants(truth) -> np.ndarray:
    """``(90, 90, 3)`` float64: per node and channel ``sum(1/f) / sum(1/f^2)`` over the valid phi_d
    cells with f > 0 (Eq. 1's cells); NaN where there is none."""
    valid = truth.valid_mask()[..., None] & (np.nan_to_num(truth.table, nan=0.0) > 0.0)
    inverse = np.where(valid, 1.0 / np.where(valid, truth.table, 1.0), 0.0).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(valid.any(axis=2), inverse.sum(axis=2) / (inverse**2).sum(axis=2), np.nan)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("materials", nargs="*", help=f"MERL-NBRDF names (default: {' '.join(MATERIALS)})")
    names = parser.parse_args().materials or list(MATERIALS)
    print("| material | exact floor (phi_d mean) | Eq. 1 of sum(1/f) / sum(1/f^2) per node |\n|---|---:|---:|")
    for name in names:
        truth = nbrdf.nbrdf_merl(name)
        optimal = metrics.BRDFErrors(truth)(eq1_optimal_constants(truth))["eq1"]
        print(f"| {name} | {bivariate.exact_floor(truth):.4f} | {optimal:.4f} |", flush=True)


if __name__ == "__main__":
    main()
