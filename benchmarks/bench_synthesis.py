"""Linear solve against analysis by synthesis: relight error against wall time, per material.

For each material: the input sphere (128 px, 128 spp, path traced) under grace_latlong_1k; the
linear route (:func:`mi_bivariate.recover.recover`, timed stages observations + lighting matrix +
adequacy + solve; also at 1/8, 1/4 and 1/2 of its sampled normals and directions, and at these and
its own on a grid of half the side (16 x 16, with priors learnt on it, leave-one-out), median of 3
each: the linear route's own curve of error against time) and analysis by synthesis
(:func:`mi_bivariate.synthesis.analysis_by_synthesis`: Adam on log f through ``prb`` with table
importance sampling, from the Lambertian fit) for ``--time-factor`` x the linear route's time.
Every table is rendered under pisa_256 exactly as the 3D truth is, by the evaluation's renderer
(the converged quadrature of ``mi_bivariate.reference`` at its novel resolution, 64 px; the own
noise of the truth's, the linear table's and AbS's best table's renders is measured at two other
seeds and printed) and compared (relative RMSE, beside the exact
reduction's: the relight floor); the clock stops while errors are measured. One setting of the
optimiser for every material (chosen on gold-metallic-paint3's training loss).

Time to equal error is, for each route, the least time at which it reached the error: the ratio
"linear reaches AbS best" is AbS's time to its best relight error over the default linear route's
time, and "fastest linear run" the same over the fastest linear run (ladder included) at least as
good. Prints one table (time-to-equal-error ratios) and writes the records (JSON lines) and the
figure ``docs/figures/abs_vs_solve.png`` (relight error against wall time).

    MI_BIVARIATE_DATA=/work/shared/data python benchmarks/bench_synthesis.py \
        [--materials gold-metallic-paint3 blue-acrylic red-phenolic] [--time-factor 20] [--out out/abs] [--grid 16 16]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path
from typing import List, Sequence

from _machine import machine as _machine  # benchmarks/_machine.py

ROOT = Path(__file__).resolve().parents[1]
MATERIALS = ("gold-metallic-paint3", "blue-acrylic", "red-phenolic")
NOVEL = "pisa_256"


def machine() -> str:
    return _machine()


def ratio_row(r: dict) -> str:
    lin, a = r["linear"], r["abs"]
    best, t_best = a["best_relight"], a["best_relight_time_s"]
    if lin["relight"] <= best and a.get("best_relight_iteration") == 0:
        ratio = "no ratio: AbS never beat its start"  # its best at time 0 (not "0x")
    elif lin["relight"] <= best:
        # The linear route is at least as good as AbS's best: it got there in its own time.
        ratio = f"{t_best / lin['time_s']:.1f}x (AbS best at {t_best:.1f} s)"
    else:
        ratio = "AbS better"
    reached = a["time_to_linear_relight_s"]
    equal = ("at its start (0 s)" if reached == 0 else f"{reached / lin['time_s']:.1f}x" if reached is not None
             else f"> {a['time_s'] / lin['time_s']:.0f}x (not reached in {a['time_s']:.0f} s)")
    floor = f"{r['relight_floor']:.4f}" if "relight_floor" in r else "-"
    return (f"| {r['material']} | {lin['time_s']:.2f} | {lin['relight']:.4f} | {floor} | {a['start_relight']:.4f} | "
            f"{best:.4f} | {a['iterations']} | {a['time_s']:.1f} | {ratio} | {fastest_row(r)} | {equal} | "
            f"{loss(a['loss_first'])} -> {loss(a['loss_last'])} |")


def loss(value) -> str:
    return "-" if value is None else f"{value:.3f}"


def fastest_row(r: dict) -> str:
    """The fastest linear run (ladder included) that reaches AbS's best relight error, as a table cell."""
    if "linear_to_abs_best" not in r:
        return "(not measured)"
    fastest = r["linear_to_abs_best"]
    if fastest is None:
        return "AbS better"
    ratio = f"{r['ladder_speedup']:.0f}x" if r.get("ladder_speedup") is not None else "-"
    from mi_bivariate.synthesis import rung_label  # lazy, as in main(): --help stays fast

    return f"{ratio} ({rung_label(fastest)}: {fastest['time_s']:.2f} s, {fastest['relight']:.4f})"


def plot(records: Sequence[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mi_bivariate.atomic import atomic_path

    fig, axes = plt.subplots(1, len(records), figsize=(5.0 * len(records), 4.0), squeeze=False)
    for ax, r in zip(axes[0], records):
        trace = r["trace"]
        t = [max(row["time_s"], 1e-2) for row in trace]
        ax.plot(t, [row["relight"] for row in trace], "-o", ms=2.5, label="analysis by synthesis (Adam + prb)")
        lin = r["linear"]
        ladder = r.get("linear_ladder", [])
        if ladder:
            top = max(p["n_normals"] for p in ladder + [lin])
            own = lin.get("grid")
            labelled = set()
            for p in sorted(ladder, key=lambda p: p["n_normals"]):
                coarse = own is not None and p.get("grid", own) != own
                label = (f"linear solve on a {p['grid'][0]} x {p['grid'][1]} grid, M and K as marked" if coarse
                         else "linear solve, fewer normals M and directions K (larger: fewer)")
                ax.plot([p["time_s"]], [p["relight"]], "r^" if coarse else "rs", mfc="none",
                        ms=4 + 3 * math.log2(top / p["n_normals"]), label=None if label in labelled else label)
                labelled.add(label)
        star = (f"linear solve, M {lin['n_normals']}" + (f", {lin['grid'][0]} x {lin['grid'][1]}" if "grid" in lin else "")
                if "n_normals" in lin else "linear solve (defaults)")
        ax.plot([lin["time_s"]], [lin["relight"]], "r*", ms=12, label=star)
        ax.axhline(lin["relight"], color="r", lw=0.8, ls="--")
        if "relight_floor" in r:
            ax.axhline(r["relight_floor"], color="0.4", lw=0.8, ls=":", label="exact reduction (relight floor)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("wall time (s), clock paused for evaluation")
        ax.set_ylabel(f"relight error under {r['novel_probe']} (rel. RMSE)")
        ax.set_title(r["material"], fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(3, len(labels)), fontsize=8, frameon=False)
    scoring = records[0].get("scoring", {"renderer": "path"})
    how = ("converged quadrature (mi_bivariate.reference)" if scoring["renderer"] == "reference"
           else "path traced, same seed")
    fig.suptitle(f"input {records[0]['input_probe']}; truth and tables rendered alike: {how}", fontsize=9)
    fig.tight_layout(rect=(0, 0.11, 1, 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def main(argv: Sequence[str] = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--materials", nargs="+", default=list(MATERIALS))
    parser.add_argument("--time-factor", type=float, default=20.0,
                        help="AbS budget in multiples of the linear route's time")
    parser.add_argument("--budget", type=float, default=None, help="AbS budget in seconds (overrides)")
    parser.add_argument("--eval-every", type=int, default=10)
    parser.add_argument("--quick", action="store_true", help="the evaluation's quick config (48 px, 12 x 12)")
    parser.add_argument("--grid", type=int, nargs=2, metavar=("N_T", "N_S"), default=None,
                        help="the st grid of both routes (AbS's table and the linear route's; default: the config's)")
    parser.add_argument("--out", default=str(ROOT / "out" / "abs"))
    parser.add_argument("--figure", default=str(ROOT / "docs" / "figures" / "abs_vs_solve.png"))
    parser.add_argument("--replot", action="store_true", help="only redraw the figure from --out's records")
    args = parser.parse_args(argv)

    from mi_bivariate import evaluate as ev
    from mi_bivariate import synthesis

    out = Path(args.out)
    path = out / "abs_vs_solve.jsonl"
    records: List[dict] = []
    if args.replot:
        # A rerun into the same --out appends: the last record of each material is the one shown.
        latest = {}
        for line in path.read_text().splitlines():
            if line.strip():
                r = json.loads(line)
                latest[r["material"]] = r
        records = list(latest.values())
    else:
        print(f"Machine: {machine()}")
        config = ev.EvalConfig.quick(shared_data=True) if args.quick else ev.EvalConfig()
        if args.grid is not None:
            config = dataclasses.replace(config, grid=tuple(args.grid))
        print(f"Grid of both routes: {config.grid[0]} x {config.grid[1]}")
        out.mkdir(parents=True, exist_ok=True)
        for material in args.materials:
            r = synthesis.analysis_by_synthesis(material, "grace_latlong_1k", config=config, novel_probe=NOVEL,
                                                time_factor=args.time_factor, budget_s=args.budget,
                                                eval_every=args.eval_every)
            records.append(r)
            ev.append_record(path, r)
            print(f"{material}: linear {r['linear']['time_s']:.2f} s relight {r['linear']['relight']:.4f}; "
                  f"AbS best {r['abs']['best_relight']:.4f} at {r['abs']['best_relight_time_s']:.1f} s "
                  f"of {r['abs']['time_s']:.1f} s", flush=True)
            print(f"  priors of the linear route: {r['linear']['prior']}", flush=True)
            noise = r["relight_noise"]
            print(f"  relight floor (exact reduction) {r['relight_floor']:.4f}; one render's own noise (rel. RMS): "
                  + ", ".join(f"{k.replace('_', ' ')} {v:.5f}" for k, v in noise.items()), flush=True)
            for rung in r["linear_ladder"] + [r["linear"]]:
                stages = ", ".join(f"{k} {v:.2f}" for k, v in rung["stages"].items())
                print(f"  linear at {synthesis.rung_label(rung)}: {rung['time_s']:.2f} s "
                      f"(runs {', '.join(f'{t:.2f}' for t in rung['times_s'])}; medians: {stages}), "
                      f"relight {rung['relight']:.4f}", flush=True)
        print(f"\nMachine after the run: {machine()}")
    print("\n| material | linear time (s) | linear relight | relight floor | AbS start relight | AbS best relight "
          "| AbS iterations | AbS time (s) | linear reaches AbS best | fastest linear run reaching AbS best "
          "| AbS reaches linear | AbS loss first -> last (10-it mean) |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- | --- | --- | --- |")
    for r in records:
        print(ratio_row(r))
    plot(records, Path(args.figure))
    print(f"\nrecords: {path}; figure: {args.figure}")


if __name__ == "__main__":
    main(sys.argv[1:])
