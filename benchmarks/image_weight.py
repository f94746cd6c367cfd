"""Two images (grace_latlong_1k + uffizi_256): what re-weighting the second image's rows does.

    MI_BIVARIATE_DATA=../shared/data OPENBLAS_NUM_THREADS=1 python benchmarks/image_weight.py \
        chrome-steel,red-fabric,gold-paint,red-fabric2,white-fabric,pvc,specular-red-phenolic

Row level, as benchmarks/pair_rule.py (2000 normals of a 128 px sphere, K = 8000, relit under
grace_256 / pisa_256 / pedestrian_overpass_1k, leave-one-out priors, the default solve
``solve.solve_stages``). Uffizi's rows get their sigma multiplied by each factor (weight
1 / factor^2); grace alone is the reference; the last column is ``recover``'s default,
:func:`mi_bivariate.solve.cross_image_factors` (leave-one-image-out prediction).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from ablation import NOVEL, full_table, rel, render_rows

from mi_bivariate import capture, lighting, probes, solve, training_set
from mi_bivariate.geometry import SphereGeometry
from mi_bivariate.solve import cross_image_factors, solve_stages
from mi_bivariate.variants import ensure_variant

FACTORS = (1.0, 2.0, 4.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("materials", help="comma-separated MERL-NBRDF names")
    args = parser.parse_args()
    ensure_variant()
    obs = capture.image_observations(np.ones((128, 128, 3), np.float32), SphereGeometry(64, 64, 60),
                                     n_normals=2000, seed=0, saturation=2.0)
    inputs = {p: probes.shared_probe(p) for p in ("grace_latlong_1k", "uffizi_256")}
    novel = {p: probes.shared_probe(p) for p in NOVEL}
    L_in = {p: lighting.lighting_matrix(obs, inputs[p], n_dirs=8000) for p in inputs}
    L_novel = {p: lighting.lighting_matrix(obs, novel[p], n_dirs=32768, seed=5) for p in NOVEL}
    tables = training_set.reduced_tables(32, 32)
    L = np.concatenate([L_in[p] for p in inputs])
    index = np.repeat([0, 1], len(obs))
    for name in args.materials.split(","):
        t0 = time.perf_counter()
        prior, basis = training_set.learn_priors(tables, exclude=(name,))
        table3d = full_table(name)
        I = {p: render_rows(obs, inputs[p], table3d) for p in inputs}
        truth = {p: render_rows(obs, novel[p], table3d) for p in NOVEL}
        exact = tables[name].reshape(-1, 3)
        floors = np.array([rel(np.einsum("mnc,nc->mc", L_novel[p], exact), truth[p]) for p in NOVEL])

        def ratio(table: np.ndarray) -> float:
            f = table.reshape(-1, 3)
            return float(np.median([rel(np.einsum("mnc,nc->mc", L_novel[p], f), truth[p]) for p in NOVEL] / floors))

        grace = solve.prepare_data_term(L_in["grace_latlong_1k"], I["grace_latlong_1k"])
        cells = [f"grace alone {ratio(solve_stages(grace, prior, None, basis).table):.2f}"]
        values = np.concatenate([I[p] for p in inputs])
        base = solve.row_sigma(values, index)
        for factor in FACTORS:
            sigma = base.copy()
            sigma[index == 1] *= factor
            result = solve_stages(solve.prepare_data_term(L, values, sigma), prior, None, basis)
            cells.append(f"uffizi sigma x{factor:g}: {ratio(result.table):.2f} (alpha {result.alphas[0]:.1g})")
        factors = cross_image_factors(L, values, index, base, prior, None, basis)
        result = solve_stages(solve.prepare_data_term(L, values, base * factors[index][:, None]), prior, None, basis)
        cells.append(f"cross (recover's default) {ratio(result.table):.2f} (factors {np.round(factors, 2).tolist()})")
        print(f"{name}: " + " | ".join(cells) + f" ({time.perf_counter() - t0:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
