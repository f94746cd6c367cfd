r"""How many light directions per normal K the MIS lighting matrix needs: the quadrature noise of
``L f`` against K, on exact tables, beside the solve's model error (docs/recovery.md, "Directions
per normal").

    MI_BIVARIATE_DATA=../shared/data python benchmarks/dirs_noise.py \
        [--materials tungsten-carbide,specular-white-phenolic,...] [--dirs 2000,4000,8000,32768] \
        [--probes grace_latlong_1k,uffizi_256] [--normals 3000]

For each probe and K, two lighting matrices of the row-level protocol's sphere rows
(:func:`ablation.sphere_rows`, a 128 px orthographic sphere, ``--normals`` rows) are built with
seeds 1 and 2, and one at K = 131072 (seed 9) as the converged prediction. For each material's
exact 32 x 32 reduction ``f`` (and a constant 0.1 1/sr table), printed as relative RMS over the
rows and channels:

- ``noise``: ``rel(L_1 f, L_2 f) / sqrt(2)``, one lighting matrix's own quadrature error;
- ``vs converged``: ``rel(L_1 f, L_131072 f)``, that error plus any bias against the converged
  prediction (the converged one's own noise, ~K / 131072 of the noise at K, is included).

``--seeds N``: instead, the error against the converged prediction at each K for seeds 1 to N,
one column per seed (a spike shows as one seed far above the others; recovery.md section 11's
table is ``--probes uffizi_256 --materials blue-acrylic,tungsten-carbide
--dirs 4000,5000,6000,8000,10000,16000 --seeds 4``).

``--mix U:E:P,...``: instead of K, each column is a mixture of the three strategies given as
direction counts (uniform, environment, peak; K is their sum), with the median time of one lighting
matrix of these rows beside its noise, the mean over all pairs of seeds. The mixtures alternate
within each seed, so that the machine's load falls on each alike. recovery.md section 11's table of
the environment's share is ``--mix 2000:4000:2000,1000:6000:2000,2000:8000:2000,2000:12000:2000,
1000:4000:1500,2000:2000:2000 --seeds 3``.

Both are to be read beside the solve's model error, the relative residual of a clean recovery
(~1-12%, ``recover``'s summary line): a quadrature error well below it is not what the solve fits.
Development materials only; it chooses nothing by itself (the evaluation's accuracy table decides
the default).
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import numpy as np
from ablation import rel, sphere_rows

from _machine import machine  # benchmarks/_machine.py
from mi_bivariate import lighting, probes, training_set
from mi_bivariate.lighting import mis
from mi_bivariate.variants import ensure_variant

MATERIALS = ("gold-metallic-paint3,blue-acrylic,specular-white-phenolic,tungsten-carbide,alum-bronze,"
             "white-paint,black-fabric")
CONVERGED_DIRS = 131072


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--materials", default=MATERIALS)
    parser.add_argument("--dirs", default="2000,4000,8000,32768")
    parser.add_argument("--probes", default="grace_latlong_1k,uffizi_256")
    parser.add_argument("--normals", type=int, default=3000)
    parser.add_argument("--seeds", type=int, default=0, help="per-seed errors for seeds 1..N instead")
    parser.add_argument("--mix", default="", help="columns of strategy counts U:E:P instead of --dirs")
    args = parser.parse_args()
    t0 = time.perf_counter()
    obs, tables = rows_and_tables(args)
    if args.mix:
        mix_table(args, obs, tables)
        print(f"\n{time.perf_counter() - t0:.0f} s")
        return
    dirs = [int(k) for k in args.dirs.split(",")]
    seeds = range(1, max(2, args.seeds) + 1)
    print(f"{len(obs)} rows of a 128 px sphere; seeds {seeds[0]}-{seeds[-1]} at each K; converged: "
          f"K = {CONVERGED_DIRS} (seed 9)\n")
    if args.seeds:
        print("| probe | table | K | " + " | ".join(f"seed {s}" for s in seeds) + " |")
        print("|---|---|---:|" + "---:|" * len(seeds))
    else:
        print("| probe | table | " + " | ".join(f"K = {k}: noise | vs converged" for k in dirs) + " |")
        print("|---|---|" + "---:|---:|" * len(dirs))
    for name in args.probes.split(","):
        probe = probes.shared_probe(name)
        converged = lighting.lighting_matrix(obs, probe, n_dirs=CONVERGED_DIRS, seed=9)
        truth = {t: np.einsum("mnc,nc->mc", converged, f) for t, f in tables.items()}
        del converged
        cells = {t: [] for t in tables}
        for k in dirs:
            predicted = {t: [] for t in tables}
            for seed in seeds:
                L = lighting.lighting_matrix(obs, probe, n_dirs=k, seed=seed)
                for t, f in tables.items():
                    predicted[t].append(np.einsum("mnc,nc->mc", L, f))
            for t, (p1, p2, *_) in predicted.items():
                if args.seeds:
                    print(f"| {name} | {t} | {k} | " + " | ".join(f"{100 * rel(p, truth[t]):.3f}%" for p in predicted[t])
                          + " |", flush=True)
                else:
                    cells[t].append(f"{100 * rel(p1, p2) / math.sqrt(2):.3f}% | {100 * rel(p1, truth[t]):.3f}%")
        if not args.seeds:
            for t in tables:
                print(f"| {name} | {t} | " + " | ".join(cells[t]) + " |", flush=True)
    print(f"\n{time.perf_counter() - t0:.0f} s")


def rows_and_tables(args: argparse.Namespace):
    """The variant started and the machine printed; the rows (``--normals``) and the tables: a constant one
    and each ``--materials`` exact 32 x 32 reduction, ``{name: (1024, 3)}``."""
    ensure_variant()
    print(machine())
    obs, _ = sphere_rows(args.normals)
    reduced = training_set.reduced_tables(32, 32)
    tables = {"constant 0.1": np.full((1024, 3), 0.1, np.float32)}
    tables.update({name: reduced[name].reshape(-1, 3) for name in args.materials.split(",")})
    return obs, tables


def mix_table(args: argparse.Namespace, obs, tables: dict) -> None:
    """The ``--mix`` table: per strategy mixture, the noise of ``L f`` (mean over pairs of seeds) and the
    median time of one lighting matrix of the rows (all seeds, both probes)."""
    mixes = [tuple(int(c) for c in m.split(":")) for m in args.mix.split(",")]
    seeds = range(1, max(2, args.seeds) + 1)
    pairs = [(a, b) for i, a in enumerate(seeds) for b in seeds[i + 1:]]
    default = dict(mis.MIS_FRACTIONS)
    print(f"{len(obs)} rows of a 128 px sphere; noise = rel(L_a f, L_b f) / sqrt 2, mean over {len(pairs)} pairs "
          f"of seeds {seeds[0]}-{seeds[-1]}\n")
    print("| probe | uniform : environment : peak | K | time (median) | " + " | ".join(tables) + " |")
    print("|---|---|---:|---:|" + "---:|" * len(tables))
    try:
        for name in args.probes.split(","):
            probe = probes.shared_probe(name)
            predicted = {mix: {t: [] for t in tables} for mix in mixes}
            times = {mix: [] for mix in mixes}
            for seed in seeds:  # the mixtures alternate, so that the machine's load falls on each alike
                for mix in mixes:
                    mis.MIS_FRACTIONS = dict(zip(("uniform", "environment", "peak"), mix))
                    start = time.perf_counter()
                    L = lighting.lighting_matrix(obs, probe, n_dirs=sum(mix), seed=seed)
                    times[mix].append(time.perf_counter() - start)
                    for t, f in tables.items():
                        predicted[mix][t].append(np.einsum("mnc,nc->mc", L, f))
                    del L
            for mix in mixes:
                noise = [statistics.mean(rel(p[a - 1], p[b - 1]) / math.sqrt(2) for a, b in pairs)
                         for p in predicted[mix].values()]
                print(f"| {name} | {':'.join(map(str, mix))} | {sum(mix)} | {statistics.median(times[mix]):.3f} s | "
                      + " | ".join(f"{100 * n:.3f}%" for n in noise) + " |", flush=True)
    finally:
        mis.MIS_FRACTIONS = default


if __name__ == "__main__":
    main()
