"""Where the MIS lighting matrix's kernels spend their time: per strategy and stage (issue 10).

    MI_BIVARIATE_DATA=../shared/data python benchmarks/mis_kernels.py [--rows 128]

On ``bench_speed.py``'s input (a 256 px gold-metallic-paint3 sphere under grace_latlong_1k,
K = 8000), one chunk of ``--rows`` rows: for each strategy of the ``"mis"`` mixture, the
kernel time (``dr.kernel_history``) of its lanes alone (directions, densities), then with the
radiance looked up, then with the bilinear splat, each evaluated on its own. Twice: the
environment sampled per row (``_mis_chunk`` without a pool) and from the pool
(``lighting.mis.environment_pool``, as ``lighting_matrix`` runs it). Each figure is the median
of 5 repeats after a warm-up (kernel compilation excluded).

The lanes are those of the one-lane-per-(row, direction) layout (``lighting.mis._mis_lanes``, with
``ReduceMode.Expand``): what CUDA runs, and what the CPU ran before a lane per row looped over its
directions (``docs/recovery.md``, Speed, Round 21). The per-stage split of the work holds for both.

Since the environment-density proxy (``docs/recovery.md``, Round 7) the lanes look the radiance
up themselves (the balance heuristic's environment density is read from it), so "lanes" includes
the radiance and "+ radiance" adds only the product with the weight.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys

import drjit as dr
import mitsuba as mi
from bench_speed import load_inputs

from mi_bivariate.lighting import hemisphere_offsets, kernels, mis
from mi_bivariate.recover import recover
from mi_bivariate.variants import ensure_variant

PARTS = ("lanes", "radiance", "splat")


def kernel_ms(run) -> float:
    """Summed kernel execution time (ms) of ``run()``, median of 5 after a warm-up."""
    run()
    times = []
    for _ in range(5):
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        run()
        history = dr.kernel_history()
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        times.append(sum(h.get("execution_time", 0.0) for h in history if h.get("operation_count", 0) > 0))
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rows", type=int, default=128)
    args = parser.parse_args()
    ensure_variant()
    _, probe, shot = load_inputs()
    obs = recover(shot.image, probe, shot.geometry).observations
    packets = kernels._row_packets(obs.normals, obs.views, hemisphere_offsets(len(obs), 0))[: args.rows]
    m, counts = len(packets), mis.strategy_counts(8000)
    data = kernels._row_data(packets)
    pool = mis.environment_pool(probe, counts["environment"], 0)

    def stage(strategy: str, part: str, use_pool: bool):
        def run():
            lanes = mis._mis_lanes(data, m, probe, strategy, counts, pool=pool if use_pool else None)
            row, lx, ly, lz, d, weight, sin_v, cos_v, above, pooled = lanes
            if part == "lanes":
                dr.eval(weight, d)
            else:
                radiance = dr.select(above, pooled, 0.0)
                if part == "radiance":
                    dr.eval(radiance * weight)
                else:
                    target = dr.zeros(mi.Float, m * 1024 * 4)
                    kernels._splat(m, row, lx, ly, lz, sin_v, cos_v, radiance * weight, 32, 32, active=above,
                                   target=target)
                    dr.eval(target)
            dr.sync_thread()
        return run

    print(f"{m} rows, K = 8000 ({', '.join(f'{k} {v}' for k, v in counts.items())} per row); load average "
          f"{', '.join(f'{v:.1f}' for v in os.getloadavg())}; {sys.platform}, Dr.Jit threads {dr.thread_count()}\n")
    print("| strategy | environment | lanes (ms) | + radiance (ms) | + splat (ms) |\n|---|---|---:|---:|---:|")
    totals = {False: 0.0, True: 0.0}
    for use_pool in (False, True):
        for strategy in counts:
            ms = [kernel_ms(stage(strategy, part, use_pool)) for part in PARTS]
            totals[use_pool] += ms[-1]
            print(f"| {strategy} | {'pooled' if use_pool else 'per row'} | " + " | ".join(f"{v:.1f}" for v in ms) + " |")
    print(f"\nAll strategies, splat included: per row {totals[False]:.1f} ms, pooled {totals[True]:.1f} ms "
          f"per {m} rows.")


if __name__ == "__main__":
    main()
