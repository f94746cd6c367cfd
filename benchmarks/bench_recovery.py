"""Recovery benchmark, lighting part: lighting-matrix assembly (Eqs. 3-5).

Prints a Markdown report:

1. Assembly time of L at the paper's size (M = 8000 normals, K = 32000 light
   directions, 32 x 32 st grid, RGB) with the Dr.Jit kernel, against the
   plain numpy reference (``tests/reference_lighting.py``, same directions)
   in the same run. The reference runs on a subset of rows and is
   extrapolated linearly (its cost is exactly linear in rows); the table
   says so. Peak memory of the Dr.Jit assembly is the growth of the
   process's peak RSS (``ru_maxrss``), measured before the reference runs.
   Targets: >= 40x faster than numpy, <= 2 s on 2 cores, < 2 GB.
2. Quadrature accuracy: per-pixel relative RMS change of ``L @ f`` between
   K = 32000 and K = 128000 (different seeds), and of the texel quadrature
   (:func:`texel_lighting_matrix`, probe downsampled 8x and 16x) against
   K = 128000, for a smooth (diffuse) and a sharp (0.05 rad lobe) table.

Run: ``MI_BIVARIATE_DATA=../shared/data python benchmarks/bench_recovery.py [--rows 200] [--quick]``
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path
from typing import Callable, List, Tuple

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # reference_lighting lives with the tests


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def load_probe():
    from mi_bivariate.probes import Probe, shared_probe
    from mi_bivariate.sources import synthetic_environment

    try:
        return shared_probe("grace_latlong_1k"), "grace_latlong_1k (1024 x 512)"
    except Exception:  # no shared data: the demo's procedural environment
        return Probe(synthetic_environment(seed=1), source="synthetic"), "synthetic environment (no shared data)"


def sphere_observations(n: int):
    """``n`` observations: Fibonacci normals over the 80-degree cap, camera on +z."""
    from mi_bivariate.capture import Observations, hemisphere_lattice

    lattice = hemisphere_lattice(int(round(n / (1 - np.cos(np.radians(80))))) + 8)
    normals = lattice[lattice[:, 2] >= np.cos(np.radians(80))][:n]
    views = np.broadcast_to([0.0, 0.0, 1.0], normals.shape).copy()
    return Observations(normals, views, np.zeros((len(normals), 3), np.float32), np.zeros(len(normals), np.int32))


def tables(n_t: int = 32, n_s: int = 32) -> List[Tuple[str, np.ndarray]]:
    from mi_bivariate.coordinates import grid_nodes, half_diff_from_st

    theta_h, theta_d = half_diff_from_st(grid_nodes(n_s)[None, :], grid_nodes(n_t)[:, None])
    diffuse = np.broadcast_to(np.array([0.5, 0.4, 0.3]) / np.pi, (n_t, n_s, 3))
    fresnel = 0.04 + 0.96 * (1.0 - np.cos(theta_d)) ** 5
    sharp = diffuse * 0.2 + (20.0 * np.exp(-(theta_h / 0.05) ** 2) * (1 + fresnel))[..., None]
    return [("smooth (diffuse)", np.ascontiguousarray(diffuse)), ("sharp (0.05 rad lobe)", sharp)]


def rel_rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean((a - b) ** 2)) / np.sqrt(np.mean(b**2)))


def timed(fn: Callable[[], object]) -> Tuple[float, object]:
    start = time.perf_counter()
    out = fn()
    return time.perf_counter() - start, out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=100, help="rows of the numpy reference to time")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats of the Dr.Jit assembly")
    parser.add_argument("--quick", action="store_true", help="skip the accuracy section")
    args = parser.parse_args()

    import drjit as dr
    from reference_lighting import lighting_matrix_reference

    from mi_bivariate import lighting
    from mi_bivariate.variants import ensure_variant

    variant = ensure_variant()
    probe, probe_name = load_probe()
    m, k, n_t, n_s = 8000, 32000, 32, 32
    obs = sphere_observations(m)

    # Warm up (kernel compilation and probe upload are one-off costs).
    lighting.lighting_matrix(obs.subset(slice(0, 64)), probe, n_t, n_s, k)
    rss0 = peak_rss_mb()
    wall, cpu = [], []
    for _ in range(args.repeats):
        c0 = time.process_time()
        t, L = timed(lambda: lighting.lighting_matrix(obs, probe, n_t, n_s, k))
        wall.append(t)
        cpu.append(time.process_time() - c0)
    rss1 = peak_rss_mb()

    rows = np.linspace(0, m - 1, args.rows).astype(int)
    t_ref, ref = timed(lambda: lighting_matrix_reference(obs, probe, n_t, n_s, k, rows=rows))
    t_ref_full = t_ref * m / len(rows)
    agreement = float(np.abs(L[rows] - ref).max() / np.abs(ref).max())
    best = min(wall)

    print(f"## Lighting matrix assembly: M = {m}, K = {k}, {n_t} x {n_s} grid, RGB\n")
    print(f"Variant `{variant}`, {dr.thread_count()} threads, probe {probe_name}.\n")
    print("| implementation | wall time (s) | CPU time (s) | peak memory | notes |")
    print("| --- | ---: | ---: | ---: | --- |")
    print(f"| Dr.Jit (`lighting_matrix`) | {best:.2f} (median {np.median(wall):.2f}) | {min(cpu):.2f} "
          f"| +{rss1 - rss0:.0f} MB RSS (peak {rss1:.0f} MB) | {args.repeats} runs; result {L.nbytes / 2**20:.0f} MB |")
    print(f"| numpy reference | {t_ref_full:.1f} (extrapolated) | - | - | timed on {len(rows)} of {m} rows "
          f"({t_ref:.1f} s), x {m / len(rows):.0f} |")
    print(f"\nSpeed-up: **{t_ref_full / best:.0f}x** (target >= 40x). "
          f"Max difference on the common rows: {agreement:.1e} of the largest entry. "
          f"Throughput: {m * k / best / 1e6:.0f} M (normal, direction) pairs/s. "
          "Targets: <= 2 s on 2 cores, < 2 GB.\n")

    solve_and_end_to_end(L, obs, probe, probe_name)

    if args.quick:
        return
    sub = obs.subset(np.arange(0, m, 8))
    reference = lighting.lighting_matrix(sub, probe, n_t, n_s, 128000, seed=1)
    candidates = [("sampled K = 32000", lambda: lighting.lighting_matrix(sub, probe, n_t, n_s, 32000, seed=0))]
    for factor in (8, 16):
        candidates.append((f"texels, probe / {factor} ({probe.width // factor} x {probe.height // factor})",
                           lambda f=factor: lighting.texel_lighting_matrix(sub, probe, n_t, n_s, downsample=f)))
    print(f"## Quadrature accuracy ({len(sub)} normals; per-pixel relative RMS against K = 128000)\n")
    names = [name for name, _ in tables(n_t, n_s)]
    print("| quadrature | time (s) | " + " | ".join(names) + " |")
    print("| --- | ---: | " + " | ".join("---:" for _ in names) + " |")
    for label, fn in candidates:
        t, Lc = timed(fn)
        errs = [rel_rms(np.einsum("mnc,nc->mc", Lc, f.reshape(-1, 3)),
                        np.einsum("mnc,nc->mc", reference, f.reshape(-1, 3))) for _, f in tables(n_t, n_s)]
        print(f"| {label} | {t:.2f} | " + " | ".join(f"{e:.1e}" for e in errs) + " |")


def solve_and_end_to_end(L: np.ndarray, obs, probe, probe_name: str) -> None:
    """Eq. 6 solve time on the assembled L, and `mi-bivariate recover` wall time as a user runs it."""
    import subprocess
    import sys
    import tempfile

    from mi_bivariate import images, render
    from mi_bivariate.nbrdf import nbrdf_merl
    from mi_bivariate.solve import solve

    values = np.einsum("mnc,nc->mc", L, np.full((L.shape[1], 3), 0.2, np.float32))
    times = [timed(lambda: solve(L, values))[0] for _ in range(3)]
    print(f"## Solve (Eq. 6, both weight pairs, three channels, M = {L.shape[0]}, N = {L.shape[1]})\n")
    print(f"| stage | best (s) | median (s) | target |\n| --- | ---: | ---: | --- |\n"
          f"| `solve.solve` | {min(times):.2f} | {np.median(times):.2f} | < 1 s |\n")

    with tempfile.TemporaryDirectory() as tmp:
        try:
            truth = nbrdf_merl("gold-metallic-paint3")
        except Exception:  # no shared data: an analytic material
            from mi_bivariate import analytic

            truth = analytic.to_merl(analytic.analytic_from_spec("ggx:alpha=0.1"))
        shot = render.render_sphere(render.bsdf_dict(truth), probe, resolution=256, spp=256, seed=0)
        image, probe_file = f"{tmp}/sphere.exr", f"{tmp}/probe.exr"
        images.write_exr(image, shot.image)
        probe.save_exr(probe_file)
        g = shot.geometry
        cases = [("explicit --sphere", ["--sphere", f"{g.cx},{g.cy},{g.radius}"]), ("automatic sphere fit", [])]
        print("## `mi-bivariate recover` end to end (256 x 256 image, defaults, new process each run)\n")
        print("| run | wall time (s) | with report PNG (s) | target |\n| --- | ---: | ---: | --- |")
        for label, extra in cases:
            walls = []
            for report in (False, True):
                cmd = [sys.executable, "-m", "mi_bivariate.cli", "recover", image, "--probe", probe_file,
                       "--out", f"{tmp}/out.npz", *extra] + ([] if report else ["--no-report"])
                walls.append(timed(lambda: subprocess.run(cmd, check=True, capture_output=True))[0])
            print(f"| {label} | {walls[0]:.1f} | {walls[1]:.1f} | < 10 s |")
        print(f"\nProbe {probe_name}; process start, imports and JIT compilation included.\n")


if __name__ == "__main__":
    main()
