"""Speed of `recover` and of each stage against its peers, measured in one run (issue 10).

One table, every row with its peer measured in the same process run:

- ``mi-bivariate recover --no-report`` end to end: median of 3 fresh processes (``--processes``; process start,
  imports and JIT compilation included); 256 px sphere (gold-metallic-paint3, or an analytic
  material without the shared data) under grace_latlong_1k, defaults, automatic sphere fit;
- what the report adds to ``recover``: the median of as many fresh processes with the report,
  alternating with the ``--no-report`` ones, minus theirs (what a user waits for: matplotlib's
  import, ~0.4-0.5 s, included); and its in-process time after a first call
  (:func:`mi_bivariate.report.write_recovery_report`, default ``L f`` prediction) against the
  path-traced re-render (``--report-render``);
- where one ``recover --no-report`` process spends its time: the stages ``recover()`` times
  itself (its printed ``timings``), the imports (``import mi_bivariate.commands``, the pipeline the
  CLI loads, in a fresh process) and the rest (interpreter start, variant, reading the files, the
  sphere fit, writing the table) as wall time minus those, medians of the same 3 processes;
- the lighting matrix (M ~ 6500 rows of 8000 normals, K = lighting.DEFAULT_DIRS, 32 x 32), both samplings:
  ``"uniform"`` (the paper's mirrored lattice) against the numpy reference of
  ``tests/reference_lighting.py`` (the same quadrature, timed on a subset of rows and
  extrapolated, with the largest difference), and the default ``"mis"`` against the numpy
  reference of the same estimator (``mis_lighting_matrix_reference``: the same lattices and pooled
  environment samples, everything else in float64 numpy; the like-for-like peer), against the
  uniform reference at the same K (another quadrature of the same integral: its time only) and
  against the uniform reference at K = 32000, the default before MIS (issue 10 measured 67x
  against it): 4x the directions and still less accurate than MIS at 8000
  (``env_pool.py --compare sampling``: pixel quadrature error 5-23% on sharp materials against
  0.1-0.3%);
- the normal equations (3 channels, ``solve.prepare_data_term``: by row blocks over the st nodes
  they touch, :func:`lighting.gram.weighted_gram`) against the dense route of solver v2;
- the solve as ``recover`` runs it (two stages with the
  basis prior, 2 prior variants x 3 channels each, confidence of the kept table) against
  solver v2 (``tests/reference_solve.py``, the code before issue 10, on the same normal
  equations: the largest table difference is printed) and against ``scipy.optimize.nnls`` on
  one channel and variant of the same problem, extrapolated to all channels, variants and stages;
- adequacy (:func:`mi_bivariate.adequacy.analyse` with the probe) against the SVD of the M x N
  matrix it replaced;
- ``import mi_bivariate.cli`` (``python -X importtime``), against a bare interpreter start.

The scaling table (M, K, grid, images) is ``benchmarks/bench_scaling.py``.

    MI_BIVARIATE_DATA=/work/shared/data python benchmarks/bench_speed.py

The benchmark's process turns the kernel's transparent huge pages off first, as the command line does in
its own processes (:func:`mi_bivariate.process.no_huge_pages`; docs/recovery.md Round 36), so that the
in-process stages are measured as ``recover`` runs them and not, each call again, at the cost of fresh
2 MiB pages on this VM (the lighting matrix's 80 MB array is mapped anew per call); ``--huge-pages``
keeps the kernel's setting (a program importing the toolkit without that call). The machine line says which.

On a shared machine: medians and ratios, with the load average printed. The package's
bytecode is compiled first (``compileall``): with ``PYTHONDONTWRITEBYTECODE`` set, as in some
agent shells, every fresh process would otherwise compile ~60 modules from source (~0.16 s),
which an installed package never does.
"""

from __future__ import annotations

import argparse
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
        from mi_bivariate.sources import synthetic_environment

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


def compile_bytecode() -> None:
    """Write the package's ``.pyc`` files as an install would (``PYTHONDONTWRITEBYTECODE`` may be set)."""
    subprocess.run([sys.executable, "-m", "compileall", "-q", str(ROOT / "mi_bivariate"), str(ROOT / "plugins")],
                   check=True, capture_output=True)


def _stage_timings(stdout: str) -> Dict[str, float]:
    """``recover()``'s own stage timings from the CLI's summary line ``timings: name x s, ...``."""
    line = [ln for ln in stdout.splitlines() if ln.startswith("timings:")][-1]
    out = {}
    for item in line[len("timings:"):].split(","):
        name, value, _ = item.strip().rsplit(" ", 2)
        out[name] = float(value)
    return out


def end_to_end(shot, probe, tmp: str, repeats: int = 3):
    """``recover`` in fresh processes, ``--no-report`` and with its report, alternating.

    Returns ``(median, CPU median, all walls, median stage timings, all walls with the report)``
    of the ``--no-report`` runs, and the report runs' walls: what a user waits for each.
    """
    from mi_bivariate.images import write_exr

    image, probe_file = f"{tmp}/sphere.exr", f"{tmp}/probe.exr"
    write_exr(image, shot.image)
    probe.save_exr(probe_file)
    cmd = [sys.executable, "-m", "mi_bivariate.cli", "recover", image, "--probe", probe_file,
           "--out", f"{tmp}/out.npz"]
    walls, stages, cpus, with_report = [], [], [], []
    for _ in range(repeats):
        wall, run = timed(lambda: subprocess.run(cmd + ["--no-report"], check=True, capture_output=True, text=True))
        walls.append(wall)
        cpus.append(CPU[-1])
        stages.append(_stage_timings(run.stdout))
        with_report.append(timed(lambda: subprocess.run(cmd, check=True, capture_output=True, text=True))[0])
    median_stages = {k: statistics.median(s[k] for s in stages) for k in stages[0]}
    return statistics.median(walls), statistics.median(cpus), walls, median_stages, with_report


def pipeline_import_time(repeats: int = 3) -> float:
    """``import mi_bivariate.commands`` (what ``mi-bivariate recover`` loads) in fresh processes, median."""
    code = "import time; t = time.perf_counter(); import mi_bivariate.commands; print(time.perf_counter() - t)"
    return statistics.median(float(subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                                                  text=True).stdout) for _ in range(repeats))


#: K of the uniform lattice before MIS became the default (the issue's own measurement).
OLD_DEFAULT_DIRS = 32000


def lighting_peer(obs, probe, rows: int) -> Dict[str, float]:
    """Both samplings (median of 3 each) and their numpy references on ``rows`` rows: the uniform
    quadrature's (at the default K and at the old default K = 32000) and the MIS estimator's."""
    from reference_lighting import lighting_matrix_reference, mis_lighting_matrix_reference

    from mi_bivariate import lighting

    out: Dict[str, object] = {}
    for sampling in ("uniform", "mis"):
        lighting.lighting_matrix(obs.subset(slice(0, 64)), probe, sampling=sampling)  # kernel compilation
        t, L = median_time(lambda: lighting.lighting_matrix(obs, probe, sampling=sampling))
        out[sampling], out[f"{sampling}_cpu"], out[f"L_{sampling}"] = t, cpu_median(3), L
    m = len(obs.normals)
    idx = np.linspace(0, m - 1, rows).astype(int)
    t_ref, ref = timed(lambda: lighting_matrix_reference(obs, probe, n_dirs=lighting.DEFAULT_DIRS, rows=idx))
    out.update(reference=t_ref * m / rows, rows=rows,
               agreement=float(np.abs(out["L_uniform"][idx] - ref).max() / np.abs(ref).max()))
    t_mis, ref_mis = timed(lambda: mis_lighting_matrix_reference(obs, probe, n_dirs=lighting.DEFAULT_DIRS, rows=idx))
    out.update(reference_mis=t_mis * m / rows,
               agreement_mis=float(np.abs(out["L_mis"][idx] - ref_mis).max() / np.abs(ref_mis).max()))
    t_old, _ = timed(lambda: lighting_matrix_reference(obs, probe, n_dirs=OLD_DEFAULT_DIRS, rows=idx))
    out["reference_old_default"] = t_old * m / rows
    return out


def solve_peer(L: np.ndarray, values: np.ndarray) -> Dict[str, float]:
    """The normal equations and the two-stage solve of ``recover`` (median of 3), solver v2 on the same
    problem (one run), and scipy's NNLS on one channel and variant of it."""
    import reference_solve as v2  # tests/reference_solve.py: the solver before issue 10
    from scipy.linalg import cho_factor, solve_triangular
    from scipy.optimize import nnls

    from mi_bivariate import solve as solve_mod
    from mi_bivariate.basis_prior import default_basis_prior
    from mi_bivariate.prior import default_prior
    from mi_bivariate.solve import solve_stages
    from mi_bivariate.threads import blas_threads

    prior, basis = default_prior(), default_basis_prior()

    def two_stage(mod, data, alpha=None):
        """Solver v2's two stages (the pair with the lower residual, both pairs in each stage),
        in v2 or in this package's solver asked for v2's rule: the tables must agree."""
        kwargs = {"pair_rule": "residual"} if mod is solve_mod else {}
        first = mod.solve_prepared(data, prior, alpha, **kwargs)
        if basis is None:
            return first, first
        mean, std = basis.predict(first.table, first.resolution, first.posterior_std)
        kept = first.alphas if mod is solve_mod else alpha  # solver v2 takes one number
        second = mod.solve_prepared(data, prior, kept, mean=mean, mean_std=std, **kwargs)
        second.measured  # the confidence recover() saves with the table
        return first, second


    with blas_threads():
        t_data, data = median_time(lambda: solve_mod.prepare_data_term(L, values))
        cpu_data = cpu_median(3)
        # Solver v2's data term is the dense route (one dsyrk over all M x N per channel).
        t_dense, dense = median_time(lambda: v2.prepare_data_term(L, values))
        dense_difference = max(float(np.abs(dense.gram[k] - data.gram[k]).max() / np.abs(dense.gram[k]).max())
                               for k in range(3))

        def as_recover(alpha=None):
            result = solve_stages(data, prior, alpha, basis)
            result.measured  # the confidence recover() saves with the table
            return result

        t_solve, result = median_time(as_recover)
        cpu = cpu_median(3)
        first = solve_mod.solve_prepared(data, prior)
        # Solver v2 had no alpha rule: both run at the alpha the discrepancy principle chose here.
        chosen = float(first.alphas[0])
        t_given, _ = timed(lambda: as_recover(chosen))
        t_same_rule, (_, result_given) = timed(lambda: two_stage(solve_mod, data, chosen))
        t_v2, (_, result_v2) = timed(lambda: two_stage(v2, dense, chosen))
    t_default, _ = timed(as_recover)  # the libraries' own BLAS threads
    stages = 2 if basis is not None else 1
    out = {"data": t_data, "data_cpu": cpu_data, "data_dense": t_dense, "data_dense_difference": dense_difference,
           "time": t_solve, "cpu": cpu, "v2": t_v2,
           "v2_difference": float(np.abs(result_given.table - result_v2.table).max() / np.abs(result_v2.table).max()),
           "given": t_given, "same_rule": t_same_rule, "chosen_alpha": chosen,
           "default_threads": t_default, "nnls": math.nan, "nnls_measured": math.nan, "nnls_share": math.nan,
           "difference": math.nan}
    try:
        pair = first.winner[1]
        regulariser = prior.regulariser(pair)
        n = data.n_nodes
        k = 1  # green, first stage
        a = data.gram[k] + first.alphas[k] / (n * data.level[k] ** 2) * (regulariser.T @ regulariser).toarray()

        def reduced_nnls() -> np.ndarray:
            # f^T A f - 2 b^T f = ||R f - R^-T b||^2 + const with A = R^T R.
            r, _ = cho_factor(a, lower=False)
            r = np.triu(r)
            return nnls(r, solve_triangular(r, data.rhs[k], trans="T"), maxiter=50 * n)[0]

        with blas_threads():
            t_nnls, x = timed(reduced_nnls)
        ours = first.pairs[pair].table.reshape(-1, 3)[:, k].astype(np.float64)
        share = 3 * (len(first.pairs) + (len(result.pairs) if stages == 2 else 0))  # stage 2: the kept pairs
        out.update(nnls_measured=t_nnls, nnls=t_nnls * share, nnls_share=share,
                   difference=float(np.abs(ours - x).max() / max(np.abs(x).max(), 1e-300)))
    except Exception as exc:  # noqa: BLE001
        out["error"] = f"{type(exc).__name__}: {exc}"
    return out


def adequacy_peer(L: np.ndarray, probe) -> Dict[str, float]:
    from mi_bivariate import adequacy

    t, report = median_time(lambda: adequacy.analyse(L, probes=[probe], warn=False))
    cpu = cpu_median(3)
    # Uncached (environment_detail caches by probe content; recover's first call per probe pays this).
    t_detail, _ = median_time(lambda: adequacy._environment_detail(probe, adequacy.DETAIL_SCALE_DEG, 40000))

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

    from mi_bivariate import lighting
    from mi_bivariate.process import configured_blas_threads
    from mi_bivariate.recover import recover
    from mi_bivariate.threads import blas_threads
    from mi_bivariate.variants import ensure_variant

    variant = ensure_variant()
    print(f"Machine: {machine()}; transparent huge pages {args.thp_state}")
    print(f"Variant {variant}, Dr.Jit threads {dr.thread_count()}, BLAS threads in heavy stages "
          f"{configured_blas_threads() or 'library default'}.\n")
    _, probe, shot = load_inputs()
    compile_bytecode()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        t_imp, t_bare = import_time()
        rows.append(("`import mi_bivariate.cli`", t_imp, math.nan, "bare `python -c pass`", t_bare, "<= 0.3 s",
                     "python -X importtime, median of 5"))
        med, cpu, walls, stages, walls_report = end_to_end(shot, probe, tmp, args.processes)
        rows.append(("`recover --no-report`, end to end", med, cpu, f"(fastest of {len(walls)})", min(walls),
                     "<= 2.0 s", "fresh processes: " + ", ".join(f"{w:.2f}" for w in walls)))
        med_report = statistics.median(walls_report)
        rows.append(("what the report adds to `recover` (fresh processes with it minus without; matplotlib's "
                     "import included)", med_report - med, math.nan, "-", math.nan, "<= 1 s",
                     f"`recover` with its report {med_report:.3f} s end to end (median of fresh processes "
                     "alternating with the `--no-report` ones: " + ", ".join(f"{w:.2f}" for w in walls_report) + ")"))
        t_pipeline = pipeline_import_time()
        with blas_threads():  # as the CLI does
            result = recover(shot.image, probe, shot.geometry)
        rep = report_peer(result, tmp)
        rows.append(("report (`L f` prediction), in process", rep["time"], rep["cpu"], "path-traced re-render",
                     rep["path_traced"], "-", "in process after its first call (matplotlib imported), PNG written"))
        obs = result.observations
        lit = lighting_peer(obs, probe, args.rows)
        m = len(obs.normals)
        rows.append((f"lighting matrix, uniform (M {m}, K {lighting.DEFAULT_DIRS}, 32 x 32)", lit["uniform"],
                     lit["uniform_cpu"],
                     "numpy reference (same quadrature)", lit["reference"], "<= 0.8 s, >= 80x",
                     f"reference on {lit['rows']} rows, extrapolated; max diff {lit['agreement']:.1e} of the "
                     "largest entry"))
        rows.append(("lighting matrix, MIS (the default)", lit["mis"], lit["mis_cpu"],
                     "numpy reference of the MIS estimator (same lattices and pool)", lit["reference_mis"],
                     "<= 0.8 s, >= 80x",
                     f"reference on {lit['rows']} rows, extrapolated; max diff {lit['agreement_mis']:.1e} of the "
                     "largest entry"))
        rows.append(("lighting matrix, MIS (the default)", lit["mis"], lit["mis_cpu"],
                     "numpy reference (uniform quadrature, same K)", lit["reference"], "-",
                     "another estimator of the same integral: its time only"))
        rows.append(("lighting matrix, MIS (the default)", lit["mis"], lit["mis_cpu"],
                     f"numpy reference, uniform K {OLD_DEFAULT_DIRS} (the default before MIS)",
                     lit["reference_old_default"], "-",
                     "4x the directions, less accurate (env_pool.py --compare sampling); on the same rows"))
        L = lit["L_mis"]
        sol = solve_peer(L, obs.values)
        rows.append(("normal equations (3 channels, `solve.prepare_data_term`: row blocks, touched nodes)",
                     sol["data"], sol["data_cpu"], "dense `dsyrk` over M x N (solver v2's route)", sol["data_dense"],
                     "-", f"same Gram matrices to {sol['data_dense_difference']:.1e} of the largest entry"))
        rows.append(("solve as recover runs it (alpha rule; stage 1: 2 variants x 3 channels, evidence; "
                     "stage 2: the kept variants; confidence)",
                     sol["time"], sol["cpu"], "the same at the chosen alpha, given (no alpha search)", sol["given"],
                     "<= 0.3 s", f"discrepancy principle chose alpha {sol['chosen_alpha']:.3g}"))
        rows.append(("solve at the chosen alpha with v2's pair rule (residual; both variants in both stages)",
                     sol["same_rule"], math.nan,
                     "solver v2 (before issue 10), same normal equations and alpha", sol["v2"], "-",
                     f"max table difference to v2 {sol['v2_difference']:.1e} of the largest entry"))
        note = (f"nnls on 1 of {sol['nnls_share']:.0f} stage x channel x variant problems "
                f"({sol['nnls_measured']:.2f} s), extrapolated; max diff {sol['difference']:.1e}"
                if "error" not in sol else sol["error"])
        rows.append(("solve as recover runs it", sol["time"], sol["cpu"], "scipy.optimize.nnls", sol["nnls"], "-",
                     note))
        rows.append(("solve, BLAS 1 thread", sol["time"], sol["cpu"], "same, default BLAS threads",
                     sol["default_threads"], "-", "oversubscription check (one run)"))
        adq = adequacy_peer(L, probe)
        rows.append(("adequacy (Gram + eigenvalues, coverage, detail cached)", adq["time"], adq["cpu"],
                     "SVD of M x N (spectrum only)", adq["svd"], "<= 0.15 s",
                     f"detail test uncached (once per probe) {adq['detail']:.3f} s; "
                     f"max spectrum diff {adq['difference']:.1e}"))
    print("| stage | ours, wall (s) | ours, CPU (s) | peer | peer, wall (s) | ratio (wall) | target | notes |")
    print("| --- | ---: | ---: | --- | ---: | ---: | --- | --- |")
    for name, ours, cpu, peer, theirs, target, note in rows:
        ratio = theirs / ours if ours > 0 and math.isfinite(theirs) else math.nan
        print(f"| {name} | {ours:.3f} | {cpu:.3f} | {peer} | {theirs:.3f} | {ratio:.1f}x | {target} | {note} |")
    print("\nWall times are medians of 3 (imports: 5; end to end: the processes its notes list); CPU = user + "
          "system seconds of this process and its children (median), which a loaded machine inflates far less "
          "than wall time.")
    print("\nStage timings of the in-process recovery: "
          + ", ".join(f"{k} {v:.3f} s" for k, v in result.timings.items()))
    inside = sum(stages.values())
    print(f"\nWhere one `recover --no-report` process spends its {med:.2f} s "
          f"(medians of the {len(walls)} fresh processes): "
          + ", ".join(f"{k} {v:.2f} s" for k, v in stages.items())
          + f"; imports of the pipeline (`import mi_bivariate.commands`, fresh process) {t_pipeline:.2f} s; "
          f"the rest (interpreter start, variant, reading the files, sphere fit, priors, writing) "
          f"{max(0.0, med - inside - t_pipeline):.2f} s.")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=80, help="rows of the numpy lighting reference to time")
    parser.add_argument("--processes", type=int, default=3,
                        help="fresh `recover` processes whose median is the end-to-end time (issue 10: 3; more "
                             "for a steadier figure on a noisy machine)")
    parser.add_argument("--huge-pages", action="store_true",
                        help="keep the kernel's transparent huge pages in this process (default: off, as the "
                             "command line's processes have them)")
    args = parser.parse_args()
    from mi_bivariate import process

    if not args.huge_pages:
        process.no_huge_pages()
    args.thp_state = _thp_state() + ("" if args.huge_pages else " (mi_bivariate.process.no_huge_pages)")
    peers(args)


def _thp_state() -> str:
    """Whether this process has transparent huge pages, as the kernel says (``THP_enabled`` of
    ``/proc/self/status``), and the kernel's policy (the bracketed word of its ``enabled`` file)."""
    try:
        policy = Path("/sys/kernel/mm/transparent_hugepage/enabled").read_text()
        policy = policy[policy.find("[") + 1:policy.find("]")] if "[" in policy else policy.strip()
    except OSError:
        policy = "n/a"
    try:
        enabled = Path("/proc/self/status").read_text().split("THP_enabled:")[1].split()[0]
    except (OSError, IndexError):
        return f"unknown in this process (the kernel's: {policy})"
    return f"{'on' if enabled == '1' else 'off'} in this process (the kernel's: {policy})"


if __name__ == "__main__":
    main()
