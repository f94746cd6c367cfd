r"""The quadrature noise of the row-level benchmarks' relit truth and floor (``ablation.py``, ``eq1_phi_d.py``).

    MI_BIVARIATE_DATA=../shared/data OPENBLAS_NUM_THREADS=1 python benchmarks/row_truth_noise.py \
        [alum-bronze,black-fabric,red-phenolic,white-paint,gold-metallic-paint3,pink-jasper] [--normals 3000]

The row-level protocol scores a table relit under ``ablation.NOVEL`` as
``rel(L_novel f, truth) / rel(L_novel f_exact, truth)``, where ``truth`` is the 3D table
through the MIS quadrature (:func:`ablation.render_rows`, 65536 directions, seed 77) and
``L_novel`` the product's lighting matrix (K = 32768, seed 5). Both are sampled, so both carry
noise. Printed per material and probe, as relative RMS over the rows:

- ``truth noise``: ``rel(truth_77, truth_78) / sqrt(2)``, one truth's own error (from two seeds);
- ``L noise``: ``rel(L_5 f_exact, L_6 f_exact) / sqrt(2)``, one lighting matrix's error on the
  exact reduction's prediction (from two seeds);
- ``floor``: ``rel(L_5 f_exact, truth_77)``, the exact reduction's relight error, the figure
  every relight ratio is divided by, and ``floor'``, the same at the other seeds
  (``rel(L_6 f_exact, truth_78)``): how far one draw of the noise moves it;
- ``noise / floor``: ``hypot(truth noise, L noise) / floor``, both noises together (they add in
  quadrature in the floor).

A ratio is trustworthy when both noises are well below the floor. Development materials only;
it chooses nothing.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
from ablation import NOVEL, full_table, rel, render_rows, sphere_rows

from mi_bivariate import lighting, probes, training_set
from mi_bivariate.variants import ensure_variant

MATERIALS = "alum-bronze,black-fabric,red-phenolic,white-paint,gold-metallic-paint3,pink-jasper"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("materials", nargs="?", default=MATERIALS)
    parser.add_argument("--normals", type=int, default=3000)
    args = parser.parse_args()
    ensure_variant()
    t0 = time.perf_counter()
    obs, _ = sphere_rows(args.normals)
    novel = {p: probes.shared_probe(p) for p in NOVEL}
    L = {(p, s): lighting.lighting_matrix(obs, novel[p], n_dirs=32768, seed=s) for p in NOVEL for s in (5, 6)}
    tables = training_set.reduced_tables(32, 32)
    print(f"{len(obs)} rows of a 128 px sphere; truth 65536 directions (seeds 77, 78), L K = 32768 (seeds 5, 6)\n")
    print("| material | probe | truth noise | L noise | floor | floor' | noise / floor | floor' / floor |")
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    worst, moved = 0.0, 0.0
    for name in args.materials.split(","):
        table3d = full_table(name)
        exact = tables[name].reshape(-1, 3)
        for p in NOVEL:
            truth = {s: render_rows(obs, novel[p], table3d, seed=s) for s in (77, 78)}
            predicted = {s: np.einsum("mnc,nc->mc", L[p, s], exact) for s in (5, 6)}
            truth_noise = rel(truth[77], truth[78]) / math.sqrt(2)
            l_noise = rel(predicted[5], predicted[6]) / math.sqrt(2)
            floor, other = rel(predicted[5], truth[77]), rel(predicted[6], truth[78])
            ratio = math.hypot(truth_noise, l_noise) / floor
            worst, moved = max(worst, ratio), max(moved, abs(other / floor - 1.0))
            print(f"| {name} | {p} | {truth_noise:.4f} | {l_noise:.4f} | {floor:.4f} | {other:.4f} | {ratio:.3f} | "
                  f"{other / floor:.3f} |", flush=True)
    print(f"\nlargest noise / floor {worst:.3f}; largest |floor' / floor - 1| {moved:.3f}; "
          f"{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
