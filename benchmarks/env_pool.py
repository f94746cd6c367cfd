"""Accuracy of the MIS lighting matrix's two shortcuts: the pooled environment directions and
the environment-density proxy (issue 10).

    MI_BIVARIATE_DATA=../shared/data OPENBLAS_NUM_THREADS=1 python benchmarks/env_pool.py \\
        --materials gold-metallic-paint3,tungsten-carbide,red-phenolic,white-paint,alum-bronze,black-fabric \\
        [--compare pool|density|sampling]

``--compare sampling``: the paper's uniform mirrored lattice at K = 32000 (the default before MIS,
and what ``tests/reference_lighting.py``, the numpy reference of ``bench_speed.py``, computes)
against the default, MIS at K = 8000; the same protocol, columns "uniform 32000" and "MIS 8000".
It says whether the numpy reference at K = 32000 is a peer of at most the default's accuracy.

``--compare density`` (the second shortcut): the balance heuristic reads the environment's density
as ``luminance(E) / Z`` from the radiance each lane looks up (``lighting.mis._mis_lanes``) instead
of Mitsuba's ``pdf_direction``; both pooled, the same protocol, columns "exact" and "proxy".

``--compare pool`` (default, the first shortcut):

``lighting_matrix`` samples the environment strategy's directions once per lattice shift
(``lighting.mis.environment_pool``, 64 shifts) instead of once per row. Both are the same
stratified, unbiased estimator per row; this measures that the change costs no accuracy, at the
default K = 8000, on the row-level protocol of ``ablation.py`` (1000 normals of a 128 px sphere,
clean input under grace_latlong_1k rendered from the 3D table, leave-one-out priors):

- pixel quadrature: ``L f_exact`` against the same prediction at K = 131072 (per-row sampling,
  another seed; its own noise, against a second seed, is printed), relative RMS and 95th
  percentile of the per-pixel luminance error, each the
  mean over 4 seeds (one seed's figure moves by ~30%: rows sharing a pooled shift make it a
  noisier statistic, not a different expectation);
- recovery: ``recover``'s solve (``solve_stages``) on each matrix (each seed), relit under grace_256,
  pisa_256 and pedestrian_overpass_1k (matrices at K = 32768), median relight error / floor,
  the mean over the seeds.

Development materials; it chooses nothing (the pool was chosen for speed, this checks it).
"""

from __future__ import annotations

import argparse

import numpy as np
from ablation import NOVEL, material_rows, rel, sphere_rows

from mi_bivariate import lighting, probes, solve, training_set
from mi_bivariate.common import luminance
from mi_bivariate.lighting import _row_packets, hemisphere_offsets
from mi_bivariate.lighting.mis import _mis_chunk, environment_pool, strategy_counts
from mi_bivariate.solve import solve_stages
from mi_bivariate.variants import ensure_variant

K = 8000


def per_row_matrix(obs, probe, n_dirs: int, seed: int, chunk: int = 128) -> np.ndarray:
    """The MIS lighting matrix with the environment sampled per row (no pool)."""
    packets = _row_packets(obs.normals, obs.views, hemisphere_offsets(len(obs), seed))
    return np.concatenate([np.array(_mis_chunk(packets[i:i + chunk], probe, 32, 32, n_dirs))
                           for i in range(0, len(obs), chunk)])


def pooled_matrix(obs, probe, n_dirs: int, seed: int, env_density: str, chunk: int = 128) -> np.ndarray:
    """The MIS lighting matrix as ``lighting_matrix`` builds it (pooled environment directions),
    with the balance heuristic's environment density ``env_density`` (``"exact"`` or ``"proxy"``)."""
    packets = _row_packets(obs.normals, obs.views, hemisphere_offsets(len(obs), seed))
    pool = environment_pool(probe, strategy_counts(n_dirs)["environment"], seed)
    return np.concatenate([np.array(_mis_chunk(packets[i:i + chunk], probe, 32, 32, n_dirs, pool=pool,
                                               env_density=env_density))
                           for i in range(0, len(obs), chunk)])


def quadrature(L: np.ndarray, reference: np.ndarray, table: np.ndarray) -> tuple:
    p, r = luminance(np.einsum("mnc,nc->mc", L, table)), luminance(np.einsum("mnc,nc->mc", reference, table))
    err = np.abs(p - r) / np.maximum(r, 1e-3 * r.max())
    return rel(p, r), float(np.percentile(err, 95))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--materials", default="gold-metallic-paint3,tungsten-carbide,red-phenolic,white-paint")
    parser.add_argument("--normals", type=int, default=1000)
    parser.add_argument("--compare", choices=("pool", "density", "sampling"), default="pool")
    args = parser.parse_args()
    ensure_variant()
    obs, grace = sphere_rows(args.normals)
    novel = {p: probes.shared_probe(p) for p in NOVEL}
    seeds = range(4)
    if args.compare == "pool":
        by_seed = {"per row": [per_row_matrix(obs, grace, K, s) for s in seeds],
                   "pooled": [lighting.lighting_matrix(obs, grace, n_dirs=K, seed=s) for s in seeds]}
    elif args.compare == "sampling":
        by_seed = {"uniform 32000": [lighting.lighting_matrix(obs, grace, n_dirs=32000, seed=s, sampling="uniform")
                                     for s in seeds],
                   "MIS 8000": [lighting.lighting_matrix(obs, grace, n_dirs=K, seed=s) for s in seeds]}
    else:
        by_seed = {"exact": [pooled_matrix(obs, grace, K, s, "exact") for s in seeds],
                   "proxy": [pooled_matrix(obs, grace, K, s, "proxy") for s in seeds]}
    (first, second) = by_seed
    reference = per_row_matrix(obs, grace, 131072, 11)
    second_reference = per_row_matrix(obs, grace, 131072, 12)  # the reference's own noise
    L_novel = {p: lighting.lighting_matrix(obs, novel[p], n_dirs=32768, seed=5) for p in NOVEL}
    tables = training_set.reduced_tables(32, 32)
    print(f"| material | reference noise RMS | quadrature RMS, {first} | {second} | 95th pct, {first} | {second} "
          f"| relight / floor, {first} | {second} |\n|---|---:|---:|---:|---:|---:|---:|---:|")
    for name in args.materials.split(","):
        prior, basis, pixels, truth, floors, exact = material_rows(name, obs, grace, novel, L_novel, tables)
        cells = {}
        for tag, Ls in by_seed.items():
            ratios = []
            for L in Ls:
                f = solve_stages(solve.prepare_data_term(L, pixels), prior, None, basis).table.reshape(-1, 3)
                relit = np.array([rel(np.einsum("mnc,nc->mc", L_novel[p], f), truth[p]) for p in NOVEL])
                ratios.append(float(np.median(relit / floors)))
            quad = np.mean([quadrature(L, reference, exact) for L in Ls], axis=0)
            cells[tag] = (*quad, float(np.mean(ratios)))
        a, b = cells[first], cells[second]
        noise = quadrature(second_reference, reference, exact)[0]
        print(f"| {name} | {noise:.2%} | {a[0]:.2%} | {b[0]:.2%} | {a[1]:.2%} | {b[1]:.2%} | {a[2]:.3f} | {b[2]:.3f} |", flush=True)


if __name__ == "__main__":
    main()
