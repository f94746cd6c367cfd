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

Both are to be read beside the solve's model error, the relative residual of a clean recovery
(~1-12%, ``recover``'s summary line): a quadrature error well below it is not what the solve fits.
Development materials only; it chooses nothing by itself (the evaluation's accuracy table decides
the default).
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
from ablation import rel, sphere_rows

from _machine import machine  # benchmarks/_machine.py
from mi_bivariate import lighting, probes, training_set
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
    args = parser.parse_args()
    ensure_variant()
    t0 = time.perf_counter()
    print(machine())
    obs, _ = sphere_rows(args.normals)
    reduced = training_set.reduced_tables(32, 32)
    tables = {"constant 0.1": np.full((1024, 3), 0.1, np.float32)}
    tables.update({name: reduced[name].reshape(-1, 3) for name in args.materials.split(",")})
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


if __name__ == "__main__":
    main()
