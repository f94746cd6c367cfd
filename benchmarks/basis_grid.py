"""The basis prior on other grids: none (the default before), the 32 x 32 one resampled (now), or one learnt there.

    MI_BIVARIATE_DATA=../shared/data OPENBLAS_NUM_THREADS=1 python benchmarks/basis_grid.py --grid 48 48 \\
        --materials chrome-steel,nickel,ss440,two-layer-silver,red-specular-plastic,pink-fabric2

``recover`` resamples the packaged smoothness prior to any grid; until this measurement it used the packaged
basis prior (learnt on 32 x 32) only on 32 x 32, so a near-mirror material recovered on a finer grid
(docs/recovery.md section 6) lost the data-driven extrapolation. This measures what the three choices give, by the row-level protocol of
``benchmarks/ablation.py`` (1000 normals of a 128 px sphere, clean input under grace_latlong_1k, relit under
grace_256 / pisa_256 / pedestrian_overpass_1k as ``L_novel f``, truth by the MIS quadrature of the 3D table),
with leave-one-out priors. Every configuration uses ``recover``'s solve (discrepancy alpha, evidence pairs):

- *32 x 32, 32 x 32 basis* (today's default grid, for reference; the basis prior learnt leave-one-out,
  as every prior here);
- *grid G, no basis prior* (the default on G before: the 32 x 32 smoothness prior resampled, no basis prior);
- *grid G, basis resampled* (the default now, :meth:`mi_bivariate.basis_prior.BasisPrior.resampled`): the
  32 x 32 basis prior's mean, components and residual interpolated bilinearly in (t, s) to G's nodes;
- *grid G, both learnt on G*: what ``learn-prior --grid G`` gives (smoothness and basis prior on G).

Choose on training materials (``nbrdf.NBRDF_TRAIN_MATERIALS``); report development ones.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from ablation import NOVEL, full_table, rel, render_rows, sphere_rows  # benchmarks/ablation.py

from mi_bivariate import lighting, probes, solve, training_set
from mi_bivariate.solve import solve_stages
from mi_bivariate.variants import ensure_variant


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--materials", default="chrome-steel,nickel,ss440,two-layer-silver,red-specular-plastic,"
                                               "pink-fabric2")
    parser.add_argument("--grid", type=int, nargs=2, default=(48, 48))
    parser.add_argument("--normals", type=int, default=1000)
    args = parser.parse_args()
    ensure_variant()
    g_t, g_s = args.grid
    obs, grace = sphere_rows(args.normals)
    novel = {p: probes.shared_probe(p) for p in NOVEL}
    grids = {"32": (32, 32), "G": (g_t, g_s)}
    L_in = {k: lighting.lighting_matrix(obs, grace, n_t=t, n_s=s, n_dirs=32768) for k, (t, s) in grids.items()}
    L_novel = {k: {p: lighting.lighting_matrix(obs, novel[p], n_t=t, n_s=s, n_dirs=32768, seed=5) for p in NOVEL}
               for k, (t, s) in grids.items()}
    tables = {k: training_set.reduced_tables(t, s) for k, (t, s) in grids.items()}
    labels = ("32 x 32, 32 x 32 basis", f"{g_t} x {g_s}, no basis prior (before)",
              f"{g_t} x {g_s}, 32 x 32 basis resampled", f"{g_t} x {g_s}, both priors learnt on it")
    rows = []
    for name in args.materials.split(","):
        t0 = time.perf_counter()
        table3d = full_table(name)
        pixels = render_rows(obs, grace, table3d)
        truth = {p: render_rows(obs, novel[p], table3d) for p in NOVEL}
        prior32, basis32 = training_set.learn_priors(tables["32"], exclude=(name,))
        prior_g, basis_g = training_set.learn_priors(tables["G"], exclude=(name,))
        configs = (("32", prior32, basis32), ("G", prior32.resampled(g_t, g_s), None),
                   ("G", prior32.resampled(g_t, g_s), basis32.resampled(g_t, g_s)),
                   ("G", prior_g, basis_g))
        sigma = solve.row_sigma(pixels)
        floor = {k: [rel(np.einsum("mnc,nc->mc", L_novel[k][p], tables[k][name].reshape(-1, 3)), truth[p])
                     for p in NOVEL] for k in grids}
        errors = []
        for key, prior, basis in configs:
            data = solve.prepare_data_term(L_in[key], pixels, sigma)
            f = solve_stages(data, prior, "discrepancy", basis, "evidence").table.reshape(-1, 3)
            errors.append([rel(np.einsum("mnc,nc->mc", L_novel[key][p], f), truth[p]) for p in NOVEL])
        rows.append((name, floor, errors))
        print(f"{name}: floors 32 {np.round(floor['32'], 4).tolist()}, G {np.round(floor['G'], 4).tolist()}; "
              + "; ".join(f"{lab}: {np.round(e, 4).tolist()}" for lab, e in zip(labels, errors))
              + f" ({time.perf_counter() - t0:.0f} s)", flush=True)
    print(f"\nMedian over {', '.join(NOVEL)} of the relight error (relative RMS of L_novel f against the truth); "
          f"in brackets, over the {g_t} x {g_s} exact reduction's error (its relight floor).\n")
    print("| material | floor 32 x 32 | floor G | " + " | ".join(labels) + " |")
    print("|---|---:|---:|" + "---:|" * len(labels))
    for name, floor, errors in rows:
        fg = np.median(floor["G"])
        cells = [f"{np.median(e):.4f} ({np.median(np.array(e) / np.array(floor['G'])):.2f})" for e in errors]
        print(f"| {name} | {np.median(floor['32']):.4f} | {fg:.4f} | " + " | ".join(cells) + " |")
    ratios = np.array([[np.median(np.array(e) / np.array(floor["G"])) for e in errors] for _, floor, errors in rows])
    print("| **median / floor G** | | | " + " | ".join(f"**{v:.2f}**" for v in np.median(ratios, axis=0)) + " |")


if __name__ == "__main__":
    main()
