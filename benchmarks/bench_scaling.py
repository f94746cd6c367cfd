"""How `recover`'s stages scale: time and peak memory as M, K, the grid and the images grow (issue 10).

One fresh process per point (so each peak RSS is that point's); the input renders are made
once by the parent (32 spp: only timing matters) and passed as ``.npz`` files. Stages are
``recover``'s own timings: observations, lighting matrix, adequacy, the normal equations and
the solve (two stages with the basis prior). Prints one table, the fitted growth exponent per
stage (slope of log time against log size; size = rows for M and images, nodes for the grid,
K for K) and a peak-memory model with the problem size at which this machine's memory runs out.

    MI_BIVARIATE_DATA=/work/shared/data python benchmarks/bench_scaling.py          # a few minutes
    MI_BIVARIATE_DATA=/work/shared/data python benchmarks/bench_scaling.py --full   # the full sweeps

Default sweeps (base M 2000 normals, K 8000, grid 32, 1 image): M 2k/8k/32k, K 8k/32k/128k,
grid 16/32/64, images 1/2/4. ``--full`` uses a M 8000, K 32000 base and five values per factor.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
from typing import Dict, List

import numpy as np
from bench_speed import load_inputs, machine, peak_rss_mb, timed  # benchmarks/bench_speed.py

SCALING_PROBES = ("grace_latlong_1k", "uffizi_256", "pisa_256", "venice_sunset_1k")


def scaling_point(spec: dict) -> dict:
    """One point, in this (fresh) process: per-stage times and peak RSS.

    The input renders come from ``spec["inputs"]`` (``.npz`` files written by the parent) so that
    this process's peak memory is the recovery's, not the renderer's.
    """
    import warnings

    from mi_bivariate.geometry import SphereGeometry
    from mi_bivariate.probes import shared_probe
    from mi_bivariate.recover import recover
    from mi_bivariate.threads import blas_threads
    from mi_bivariate.variants import ensure_variant

    ensure_variant()
    images, probes, geometries = [], [], []
    for name in SCALING_PROBES[:spec["images"]]:
        if "inputs" in spec:
            with np.load(spec["inputs"][name]) as z:
                images.append(np.array(z["image"]))
                geometries.append(SphereGeometry(*(float(v) for v in z["sphere"])))
            probes.append(shared_probe(name))
        else:
            _, probe, shot = load_inputs(name, resolution=spec["resolution"], spp=32)  # timing only
            images.append(shot.image)
            probes.append(probe)
            geometries.append(shot.geometry)
    import tracemalloc

    rss0 = peak_rss_mb()
    tracemalloc.start()  # numpy reports its buffers to tracemalloc; Dr.Jit's are not seen
    with warnings.catch_warnings(), blas_threads():
        warnings.simplefilter("ignore")
        t, result = timed(lambda: recover(images, probes, geometries, n_normals=spec["M"], n_dirs=spec["K"],
                                          grid=(spec["grid"], spec["grid"]), keep_inputs=False))
    numpy_peak = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    return {**{k: v for k, v in spec.items() if k != "inputs"}, "total": t, "rss_before_mb": rss0,
            "peak_rss_mb": peak_rss_mb(), "numpy_peak_mb": numpy_peak, "rows": int(len(result.observations.values)),
            **{k: float(v) for k, v in result.timings.items() if isinstance(v, (int, float))}}


def scaling_inputs(tmp: str, count: int, resolution: int) -> Dict[str, str]:
    """Render the scaling inputs once (32 spp: only timing matters) as ``.npz`` files."""
    paths = {}
    for name in SCALING_PROBES[:count]:
        _, _, shot = load_inputs(name, resolution=resolution, spp=32)
        g = shot.geometry
        paths[name] = f"{tmp}/{name}.npz"
        np.savez(paths[name], image=shot.image, sphere=np.array([g.cx, g.cy, g.radius]))
    return paths


def scaling(args: argparse.Namespace) -> None:
    if args.full:
        base = {"M": 8000, "K": 32000, "grid": 32, "images": 1, "resolution": 256}
        sweeps = {"M": [2000, 4000, 8000, 16000, 32000], "K": [8000, 16000, 32000, 64000, 128000],
                  "grid": [16, 32, 48, 64], "images": [1, 2, 3, 4]}
    else:  # the ranges at their ends and middle, on a small base: a few minutes
        base = {"M": 2000, "K": 8000, "grid": 32, "images": 1, "resolution": 256}
        sweeps = {"M": [2000, 8000, 32000], "K": [8000, 32000, 128000], "grid": [16, 32, 64], "images": [1, 2, 4]}
    stages = ("observations", "lighting matrix", "adequacy", "normal equations", "solve")
    tmp = tempfile.mkdtemp(prefix="bench_speed_")
    base["inputs"] = scaling_inputs(tmp, max(sweeps["images"]), base["resolution"])
    print(f"\n## Scaling (one fresh process per point; base M {base['M']}, K {base['K']}, "
          f"grid {base['grid']}, 1 image; {'full' if args.full else 'default'} sweep)\n")
    print("| factor | value | rows M | " + " | ".join(f"{s} (s)" for s in stages)
          + " | total (s) | peak RSS (MB) | recover's numpy peak (MB) | L size (MB) |")
    print("| --- | ---: | ---: | " + " | ".join("---:" for _ in stages) + " | ---: | ---: | ---: | ---: |")
    fits, every = {}, []
    for factor, values in sweeps.items():
        points = []
        for v in values:
            spec = {**base, factor: v}
            cmd = [sys.executable, __file__, "--point", json.dumps(spec)]
            try:
                proc = subprocess.run(cmd, capture_output=True, text=True, timeout=args.point_timeout)
            except subprocess.TimeoutExpired:
                print(f"| {factor} | {v} | timed out after {args.point_timeout:.0f} s |", flush=True)
                continue
            if proc.returncode != 0:
                print(f"| {factor} | {v} | failed: {proc.stderr.strip().splitlines()[-1] if proc.stderr else proc.returncode} |")
                continue
            p = json.loads(proc.stdout.strip().splitlines()[-1])
            p["recover_mb"] = max(p.get("numpy_peak_mb", 0.0), 1.0)
            points.append(p)
            every.append(p)
            l_mb = p["rows"] * p["grid"] ** 2 * 3 * 4 / 2**20
            print(f"| {factor} | {v} | {p['rows']} | " + " | ".join(f"{p.get(s, math.nan):.3f}" for s in stages)
                  + f" | {p['total']:.2f} | {p['peak_rss_mb']:.0f} | {p['recover_mb']:.0f} "
                  f"| {l_mb:.0f} |", flush=True)
        if len(points) >= 2:
            size = np.log([p["grid"] ** 2 if factor == "grid" else p["rows"] if factor in ("M", "images")
                           else p[factor] for p in points])
            fits[factor] = {s: float(np.polyfit(size, np.log([max(p.get(s, 1e-9), 1e-9) for p in points]), 1)[0])
                            for s in (*stages, "total", "recover_mb")}
    print("\nFitted growth exponent (time ~ size^b; size = rows for M and images, nodes for the grid):\n")
    print("| factor | " + " | ".join(stages) + " | total | recover's numpy peak |")
    print("| --- | " + " | ".join("---:" for _ in stages) + " | ---: | ---: |")
    for factor, b in fits.items():
        print(f"| {factor} | " + " | ".join(f"{b[s]:.2f}" for s in stages)
              + f" | {b['total']:.2f} | {b['recover_mb']:.2f} |")


    memory_model(every)


def memory_model(points: List[dict]) -> None:
    """Fit peak RSS ~ a + b (rows x nodes) + c nodes^2 and say where it reaches this machine's memory."""
    if len(points) < 4:
        return
    mn = np.array([p["rows"] * p["grid"] ** 2 for p in points], float)
    nn = np.array([p["grid"] ** 4 for p in points], float)
    peak = np.array([p["peak_rss_mb"] for p in points], float)
    design = np.stack([np.ones_like(mn), mn, nn], axis=1)
    (a, b, c), *_ = np.linalg.lstsq(design, peak, rcond=None)
    total_mb = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**20
    print(f"\nPeak memory model (least squares over the {len(points)} points): peak RSS ~ {a:.0f} MB + "
          f"{b * 1e6:.1f} MB per million (row x node) + {c * 1e6:.2f} MB per million node^2. "
          f"This machine has {total_mb / 1024:.1f} GiB.")
    for grid in (32, 64, 96, 128):
        n = grid * grid
        rows = (total_mb - a - c * n * n) / max(b * n, 1e-30)
        limit = f"{rows:,.0f} rows" if rows > 0 else "not even one row (the N x N matrices alone exceed it)"
        print(f"- grid {grid} x {grid}: memory runs out at about {limit} (M x images)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true", help="the full sweeps (M 8000, K 32000 base; long)")
    parser.add_argument("--point-timeout", type=float, default=900.0, help="seconds per point")
    parser.add_argument("--point", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.point:
        print(json.dumps(scaling_point(json.loads(args.point))))
        return
    print(f"Machine: {machine()}")
    scaling(args)


if __name__ == "__main__":
    main()
