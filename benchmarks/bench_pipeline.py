"""Per-stage timings of the pipeline and their growth with M, K and the grid size.

Stages: render the input (``merl`` plugin), observations, assemble the
lighting matrix L, adequacy analysis, the constrained solve, and the re-render
of the recovery (``bivariate`` plugin). One factor grows at a time from the
base point (M normals, K light directions per normal, n_t x n_s grid nodes)
by 1x, 2x and 4x; the 4x point of each factor is M = 8000, K = 32000, 32 x 32
(the defaults when it was written; ``recover``'s K is now 8000). Prints a Markdown table with the machine.

    MI_BIVARIATE_DATA=../shared/data python benchmarks/bench_pipeline.py [--repeat 3] [--out table.md]
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

from _machine import machine as _machine  # benchmarks/_machine.py

BASE = {"M": 2000, "K": 8000, "nodes": 256}


def grid_for(nodes: int) -> tuple:
    n = int(round(math.sqrt(nodes)))
    return n, n


def machine() -> str:
    import drjit as dr
    import mitsuba as mi

    return _machine(f"Mitsuba {mi.__version__} ({mi.variant()}), Dr.Jit {dr.__version__}, "
                    f"{dr.thread_count()} Dr.Jit threads")


def run_point(truth, probe, M: int, K: int, nodes: int, resolution: int, spp: int) -> dict:
    from mi_bivariate import render
    from mi_bivariate.recover import recover

    t0 = time.perf_counter()
    shot = render.render_sphere(render.bsdf_dict(truth), probe, resolution=resolution, spp=spp, seed=0)
    t_render = time.perf_counter() - t0
    rec = recover(shot.image, probe, shot.geometry, n_normals=M, n_dirs=K, grid=grid_for(nodes), seed=0,
                  keep_inputs=False)
    t0 = time.perf_counter()
    render.render_sphere(render.bsdf_dict(rec.brdf), probe, resolution=resolution, spp=spp, seed=1)
    t_rerender = time.perf_counter() - t0
    return {"render input": t_render, "observations": rec.timings.get("observations", 0.0),
            "lighting matrix": rec.timings.get("lighting matrix", 0.0),
            "adequacy": rec.timings.get("adequacy", 0.0),
            "solve": rec.timings.get("normal equations", 0.0) + rec.timings.get("solve", 0.0),
            "re-render": t_rerender}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=1, help="runs per point (median reported)")
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--material", default="gold-metallic-paint3")
    parser.add_argument("--probe", default="grace_latlong_1k")
    parser.add_argument("--out", default=None, help="also write the Markdown table here")
    args = parser.parse_args()

    from mi_bivariate import evaluate
    from mi_bivariate.variants import ensure_variant

    ensure_variant()
    header = machine()
    if evaluate.have_shared_data():
        truth = evaluate.load_truth(evaluate.MaterialSpec(args.material, "nbrdf", args.material))
        probe = evaluate.load_probe(args.probe)
    else:
        truth = evaluate.load_truth(evaluate.MaterialSpec("ggx", "analytic", evaluate.QUICK_ANALYTIC[0]))
        probe = evaluate.load_probe("synthetic:1")
    # Warm-up: first-use JIT compilation and plugin set-up are not part of a stage's cost.
    run_point(truth, probe, 500, 1000, 64, 32, 4)

    points = [("base", BASE)]
    for factor in ("M", "K", "nodes"):
        for scale in (2, 4):
            points.append((f"{factor} x{scale}", {**BASE, factor: BASE[factor] * scale}))
    stages = ("render input", "observations", "lighting matrix", "adequacy", "solve", "re-render")
    lines = [f"Machine: {header}. Input and re-render {args.resolution}x{args.resolution} at {args.spp} spp; "
             f"median of {args.repeat} run(s); seconds.", "",
             "| point | M | K | grid | " + " | ".join(stages) + " | total |",
             "|---|---:|---:|---|" + "---:|" * (len(stages) + 1)]
    for name, p in points:
        runs = [run_point(truth, probe, p["M"], p["K"], p["nodes"], args.resolution, args.spp)
                for _ in range(args.repeat)]
        med = {s: statistics.median(r[s] for r in runs) for s in stages}
        n_t, n_s = grid_for(p["nodes"])
        lines.append(f"| {name} | {p['M']} | {p['K']} | {n_t}x{n_s} | "
                     + " | ".join(f"{med[s]:.2f}" for s in stages) + f" | {sum(med.values()):.2f} |")
        print(lines[-1], flush=True)
    table = "\n".join(lines)
    print()
    print(table)
    if args.out:
        from mi_bivariate.atomic import atomic_path

        with atomic_path(args.out) as tmp:
            tmp.write_text(table + "\n")


if __name__ == "__main__":
    main()
