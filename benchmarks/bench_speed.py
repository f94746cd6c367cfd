"""Speed of `recover` and of each stage against its peers, measured in one run; and how it scales.

One table (issue 10's targets), every row with its peer measured in the same process run:

- ``mi-bivariate recover --no-report`` end to end: median of 3 fresh processes (process start,
  imports and JIT compilation included); 256 px sphere (gold-metallic-paint3, or an analytic
  material without the shared data) under grace_latlong_1k, defaults, automatic sphere fit;
- the report: in-process time of :func:`mi_bivariate.report.write_recovery_report` (default:
  ``L f`` prediction) against the path-traced re-render (``--report-render``);
- the lighting matrix (M = 8000, K = 32000, 32 x 32) against the numpy reference of
  ``tests/reference_lighting.py`` timed on a subset of rows and extrapolated;
- the solve (:func:`mi_bivariate.solve.solve` as it is: all channels and prior variants) against
  ``scipy.optimize.nnls`` on the same problem (normal equations + prior penalty of one channel and
  one prior variant, Cholesky-reduced to a square least-squares problem, extrapolated to all
  channels and variants), with the largest difference of the two solutions;
- adequacy (:func:`mi_bivariate.adequacy.analyse` with the probe) against the SVD of the M x N
  matrix it replaced;
- ``import mi_bivariate.cli`` (``python -X importtime``), against a bare interpreter start.

Then (``--scaling``) a table of per-stage time and peak memory as M, K, the grid and the number of
images grow (one fresh process per point), with the fitted growth exponent per stage (slope of
log time against log size). ``--quick`` uses smaller sweeps.

    MI_BIVARIATE_DATA=/work/shared/data python benchmarks/bench_speed.py [--scaling] [--quick]

On a shared machine: medians and ratios, with the load average printed.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable, Dict, List, Tuple

import numpy as np
from _machine import machine as _machine  # benchmarks/_machine.py

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # reference_lighting lives with the tests

MATERIAL = "gold-metallic-paint3"
PROBE = "grace_latlong_1k"
SCALING_PROBES = ("grace_latlong_1k", "uffizi_256", "pisa_256", "venice_sunset_1k")


def machine() -> str:
    return _machine(f"numpy {np.__version__}")


#: CPU seconds (this process and its finished children) of each timed() call, latest last.
CPU: List[float] = []


def _cpu_now() -> float:
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def timed(fn: Callable[[], object]) -> Tuple[float, object]:
    """``(wall seconds, result)``; the CPU seconds go to :data:`CPU`."""
    c0 = _cpu_now()
    t0 = time.perf_counter()
    out = fn()
    wall = time.perf_counter() - t0
    CPU.append(_cpu_now() - c0)
    return wall, out


def median_time(fn: Callable[[], object], repeats: int = 3) -> Tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t, out = timed(fn)
        times.append(t)
    return statistics.median(times), out


def cpu_median(calls: int) -> float:
    """Median CPU seconds of the last ``calls`` timed() calls."""
    return statistics.median(CPU[-calls:])


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def load_inputs(probe_name: str = PROBE, resolution: int = 256, spp: int = 256):
    """``(truth BSDF dict, probe, render)`` of the benchmark sphere."""
    from mi_bivariate import render
    from mi_bivariate.probes import Probe, shared_probe

    try:
        from mi_bivariate.nbrdf import nbrdf_merl

        probe = shared_probe(probe_name)
        truth = nbrdf_merl(MATERIAL)
    except Exception:  # no shared data
        from mi_bivariate import analytic
        from mi_bivariate.demo import synthetic_environment

        probe = Probe(synthetic_environment(seed=1), source="synthetic")
        truth = analytic.to_merl(analytic.analytic_from_spec("ggx:alpha=0.1"))
    bsdf = render.bsdf_dict(truth)
    shot = render.render_sphere(bsdf, probe, resolution=resolution, spp=spp, seed=0)
    return bsdf, probe, shot


# ------------------------------------------------------------------ peers

def import_time(repeats: int = 5) -> Tuple[float, float]:
    """``(import mi_bivariate.cli, bare interpreter)`` medians in seconds (fresh processes)."""
    cum = []
    for _ in range(repeats):
        out = subprocess.run([sys.executable, "-X", "importtime", "-c", "import mi_bivariate.cli"],
                             capture_output=True, text=True, check=True).stderr
        line = [ln for ln in out.splitlines() if ln.rstrip().endswith("| mi_bivariate.cli")][-1]
        cum.append(int(line.split("|")[1]) * 1e-6)
    bare = [timed(lambda: subprocess.run([sys.executable, "-c", "pass"], check=True))[0] for _ in range(repeats)]
    return statistics.median(cum), statistics.median(bare)


def end_to_end(shot, probe, tmp: str, repeats: int = 3) -> Tuple[float, float, List[float]]:
    """``recover --no-report`` wall times in fresh processes: (median, min, all)."""
    from mi_bivariate.images import write_exr

    image, probe_file = f"{tmp}/sphere.exr", f"{tmp}/probe.exr"
    write_exr(image, shot.image)
    probe.save_exr(probe_file)
    cmd = [sys.executable, "-m", "mi_bivariate.cli", "recover", image, "--probe", probe_file,
           "--out", f"{tmp}/out.npz", "--no-report"]
    walls = [timed(lambda: subprocess.run(cmd, check=True, capture_output=True))[0] for _ in range(repeats)]
    return statistics.median(walls), cpu_median(repeats), walls


def lighting_peer(obs, probe, rows: int) -> Dict[str, float]:
    from mi_bivariate import lighting
    from reference_lighting import lighting_matrix_reference

    lighting.lighting_matrix(obs.subset(slice(0, 64)), probe)  # warm-up (kernel compilation)
    t, L = median_time(lambda: lighting.lighting_matrix(obs, probe))
    cpu = cpu_median(3)
    m = len(obs.normals)
    idx = np.linspace(0, m - 1, rows).astype(int)
    t_ref, ref = timed(lambda: lighting_matrix_reference(obs, probe, rows=idx))
    return {"time": t, "cpu": cpu, "reference": t_ref * m / rows, "rows": rows, "L": L,
            "agreement": float(np.abs(L[idx] - ref).max() / np.abs(ref).max())}


def solve_peer(L: np.ndarray, values: np.ndarray) -> Dict[str, float]:
    """:func:`solve.solve` (median of 3) and scipy's NNLS on one channel and variant of the same problem."""
    from scipy.linalg import cho_factor, solve_triangular
    from scipy.optimize import nnls

    from mi_bivariate import solve as solve_mod

    from mi_bivariate.threads import blas_threads

    with blas_threads():
        t_solve, result = median_time(lambda: solve_mod.solve(L, values))
    cpu = cpu_median(3)
    t_default, _ = timed(lambda: solve_mod.solve(L, values))  # the libraries' own BLAS threads
    out = {"time": t_solve, "cpu": cpu, "default_threads": t_default, "nnls": math.nan, "nnls_measured": math.nan, "nnls_share": math.nan,
           "difference": math.nan}
    try:  # the problem as solve.py poses it today (its internals may change: then n/a)
        from mi_bivariate.prior import default_prior

        data = solve_mod.prepare_data_term(L, values)
        pair = next(iter(result.pairs))
        prior = default_prior()
        regulariser = prior.regulariser(pair)
        n = data.n_nodes
        k = 1  # green
        a = data.gram[k] + (result.alpha / n) * (regulariser.T @ regulariser).toarray()

        def reduced_nnls() -> np.ndarray:
            # f^T A f - 2 b^T f = ||R f - R^-T b||^2 + const with A = R^T R.
            r, _ = cho_factor(a, lower=False)
            r = np.triu(r)
            return nnls(r, solve_triangular(r, data.rhs[k], trans="T"), maxiter=50 * n)[0]

        with blas_threads():
            t_nnls, x = timed(reduced_nnls)
        ours = result.pairs[pair].table.reshape(-1, 3)[:, k].astype(np.float64)
        share = len(result.pairs) * 3
        out.update(nnls_measured=t_nnls, nnls=t_nnls * share, nnls_share=share,
                   difference=float(np.abs(ours - x).max() / max(np.abs(x).max(), 1e-300)))
    except Exception as exc:  # noqa: BLE001
        out["error"] = f"{type(exc).__name__}: {exc}"
    return out


def adequacy_peer(L: np.ndarray, probe) -> Dict[str, float]:
    from mi_bivariate import adequacy

    t, report = median_time(lambda: adequacy.analyse(L, probes=[probe], warn=False))
    cpu = cpu_median(3)
    t_detail, _ = median_time(lambda: adequacy.environment_detail(probe))

    def svd_route():
        lum = L.astype(np.float64) @ np.array([0.212671, 0.715160, 0.072169])
        norms = np.linalg.norm(lum, axis=0)
        observed = norms > 1e-12 * norms.max()
        s = np.linalg.svd(lum[:, observed] / norms[observed], compute_uv=False)
        return s / s[0]

    t_svd, sigma = timed(svd_route)
    return {"time": t, "cpu": cpu, "detail": t_detail, "svd": t_svd,
            "difference": float(np.abs(report.singular_values - sigma).max())}


def report_peer(result, tmp: str) -> Dict[str, float]:
    from mi_bivariate import report

    t_pred, _ = median_time(lambda: report.write_recovery_report(result, f"{tmp}/r.png"))
    cpu = cpu_median(3)
    t_trace, _ = timed(lambda: report.write_recovery_report(result, f"{tmp}/r2.png", path_trace=True))
    return {"time": t_pred, "cpu": cpu, "path_traced": t_trace}


def peers(args: argparse.Namespace) -> None:
    import drjit as dr

    from mi_bivariate.recover import recover
    from mi_bivariate.threads import blas_threads, configured_threads
    from mi_bivariate.variants import ensure_variant

    variant = ensure_variant()
    print(f"Machine: {machine()}")
    print(f"Variant {variant}, Dr.Jit threads {dr.thread_count()}, BLAS threads in heavy stages "
          f"{configured_threads() or 'library default'}.\n")
    _, probe, shot = load_inputs()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        t_imp, t_bare = import_time()
        rows.append(("`import mi_bivariate.cli`", t_imp, math.nan, "bare `python -c pass`", t_bare, "<= 0.3 s",
                     "python -X importtime, median of 5"))
        med, cpu, walls = end_to_end(shot, probe, tmp)
        rows.append(("`recover --no-report`, end to end", med, cpu, "(fastest of 3)", min(walls), "<= 2.0 s",
                     "fresh processes: " + ", ".join(f"{w:.2f}" for w in walls)))
        with blas_threads():  # as the CLI does
            result = recover(shot.image, probe, shot.geometry)
        rep = report_peer(result, tmp)
        rows.append(("report (`L f` prediction)", rep["time"], rep["cpu"], "path-traced re-render", rep["path_traced"],
                     "<= 1 s", "in process, PNG written"))
        obs = result.observations
        lit = lighting_peer(obs, probe, args.rows)
        rows.append(("lighting matrix (M 8000, K 32000, 32 x 32)", lit["time"], lit["cpu"], "numpy reference", lit["reference"],
                     "<= 0.8 s, >= 80x", f"reference on {lit['rows']} rows, extrapolated; max diff "
                                         f"{lit['agreement']:.1e} of the largest entry"))
        L = lit.pop("L")
        sol = solve_peer(L, obs.values)
        note = (f"nnls on 1 of {sol['nnls_share']:.0f} channel x variant problems ({sol['nnls_measured']:.2f} s), "
                f"extrapolated; max diff {sol['difference']:.1e}") if "error" not in sol else sol["error"]
        rows.append(("solve (all channels, all prior variants), BLAS 1 thread", sol["time"], sol["cpu"], "scipy.optimize.nnls",
                     sol["nnls"], "<= 0.3 s", note))
        rows.append(("solve, BLAS 1 thread", sol["time"], sol["cpu"], "same, default BLAS threads", sol["default_threads"],
                     "-", "oversubscription check (one run)"))
        adq = adequacy_peer(L, probe)
        rows.append(("adequacy (Gram + eigenvalues, coverage, detail)", adq["time"], adq["cpu"], "SVD of M x N (spectrum only)",
                     adq["svd"], "<= 0.15 s", f"detail test alone {adq['detail']:.3f} s; "
                                              f"max spectrum diff {adq['difference']:.1e}"))
    print("| stage | ours, wall (s) | ours, CPU (s) | peer | peer, wall (s) | ratio (wall) | target | notes |")
    print("| --- | ---: | ---: | --- | ---: | ---: | --- | --- |")
    for name, ours, cpu, peer, theirs, target, note in rows:
        ratio = theirs / ours if ours > 0 and math.isfinite(theirs) else math.nan
        print(f"| {name} | {ours:.3f} | {cpu:.3f} | {peer} | {theirs:.3f} | {ratio:.1f}x | {target} | {note} |")
    print("\nWall times are medians of 3 (imports: 5); CPU = user + system seconds of this process and its "
          "children (median), which a loaded machine inflates far less than wall time.")
    print(f"\nStage timings of the in-process recovery: "
          + ", ".join(f"{k} {v:.3f} s" for k, v in result.timings.items()))


# ------------------------------------------------------------------ scaling

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
    base = {"M": 8000, "K": 32000, "grid": 32, "images": 1, "resolution": 256}
    if args.quick:
        sweeps = {"M": [2000, 4000, 8000], "K": [8000, 16000, 32000], "grid": [16, 24, 32], "images": [1, 2]}
        base.update(M=4000, K=16000, grid=24)
    else:
        sweeps = {"M": [2000, 4000, 8000, 16000, 32000], "K": [8000, 16000, 32000, 64000, 128000],
                  "grid": [16, 32, 48, 64], "images": [1, 2, 3, 4]}
    stages = ("observations", "lighting matrix", "adequacy", "solve")
    tmp = tempfile.mkdtemp(prefix="bench_speed_")
    base["inputs"] = scaling_inputs(tmp, max(sweeps["images"]), base["resolution"])
    print(f"\n## Scaling (one fresh process per point; base M {base['M']}, K {base['K']}, "
          f"grid {base['grid']}, 1 image; {'quick' if args.quick else 'full'} sweep)\n")
    print("| factor | value | rows M | " + " | ".join(f"{s} (s)" for s in stages)
          + " | total (s) | peak RSS (MB) | recover's numpy peak (MB) | L size (MB) |")
    print("| --- | ---: | ---: | " + " | ".join("---:" for _ in stages) + " | ---: | ---: | ---: | ---: |")
    fits = {}
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=80, help="rows of the numpy lighting reference to time")
    parser.add_argument("--scaling", action="store_true", help="also run the scaling sweeps")
    parser.add_argument("--only-scaling", action="store_true", help="only the scaling sweeps")
    parser.add_argument("--quick", action="store_true", help="smaller scaling sweeps")
    parser.add_argument("--point-timeout", type=float, default=900.0, help="seconds per scaling point")
    parser.add_argument("--point", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.point:
        print(json.dumps(scaling_point(json.loads(args.point))))
        return
    if not args.only_scaling:
        peers(args)
    if args.scaling or args.only_scaling:
        scaling(args)


if __name__ == "__main__":
    main()
