"""The issue-9 targets from an evaluation folder (results.jsonl): one table, medians over materials.

Beside each Eq. 1 ratio, the same ratio for the grid's own floor (the exact reduction sampled on
the recovery's grid): what the grid alone costs before any solve. "Observed" cells are those of
the lighting matrix's definition (every bilinear stencil node observed, ``adequacy.observed_nodes``);
"confident" cells those whose saved per-node confidence (``measured``, every channel) exceeds 0.5,
the definition issue 9's item 5 asks the scoring to use. Both are divided by the exact floor over
all cells (the paper's Fig. 3 figure) and, like for like, by the exact floor over the same cells
(the exact phi_d average scored there; records written before stop 25 lack it); the confident
cells also by the grid floor (the exact reduction on the recovery's grid) over the same cells.

    python scripts/issue9_targets.py out/evaluate [more folders] [--noisy out/evaluate_noise] [--by-input]

Several folders (e.g. the 23 development materials' evaluation and the 50 training ones') are scored
as one set of materials (results.md's "all 73" column).

``--by-input`` prints instead results.md's table of the training materials: relight / floor for each
input (grace, uffizi, both), both against the better single one (median relight errors), and the
two Eq. 1 ratios to the exact floor, with the medians.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from mi_bivariate import evaluate as ev


def load(folder: str) -> dict:
    """``{material: record}`` of a folder's configuration (config.json), the latest record of each."""
    config = json.loads((Path(folder) / "config.json").read_text())
    return {r["material"]: r for r in ev.read_records(Path(folder) / ev.RESULTS_FILE, config["config_hash"])}


def relight(entry: dict) -> float:
    return float(np.median([v["rel_rmse"] for v in entry["images"].values()]))


def ratio(entry: dict) -> float:
    """The median relight / floor over the novel probes; NaN where no floor is above the references' noise
    (the record's ratio is then null: ``metrics.MIN_RELIGHT_FLOOR``, ``metrics.NOISE_FLOOR_FACTOR``)."""
    values = [v["ratio"] for v in entry["images"].values() if v.get("ratio") is not None]
    return float(np.median(values)) if values else float("nan")


def by_input(records: dict, single: str, other: str) -> None:
    """results.md's per-input table (the training section), medians last."""
    both = f"{single}+{other}"
    print("| material | relight / floor: grace | uffizi | both | both / better single | Eq. 1 observed / exact floor "
          "| Eq. 1 f > 1e-3 / exact floor (f > 1e-3) |\n|---|---:|---:|---:|---:|---:|---:|")
    rows = []
    for name, r in sorted(records.items()):
        e, floors = r["inputs"], r["floors"]
        row = [ratio(e[single]), ratio(e[other]), ratio(e[both]),
               relight(e[both]) / min(relight(e[single]), relight(e[other])),
               e[single]["recovered"]["eq1_observed"] / floors["exact_floor"],
               e[single]["recovered"]["eq1_min"] / floors["exact_floor_min"]]
        rows.append(row)
        print(f"| {name} | " + " | ".join(f"{v:.2f}" for v in row) + " |")
    print("| **median** | " + " | ".join(f"**{v:.2f}**" for v in np.nanmedian(np.array(rows), axis=0)) + " |")
    beat = sum(row[3] < 1.0 for row in rows)
    print(f"\n{len(rows)} materials; two images better than the better single one on {beat}/{len(rows)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", help="evaluation folders, their materials scored together")
    parser.add_argument("--noisy", default=None, help="an evaluation of the same materials with --noise")
    parser.add_argument("--single", default="grace_latlong_1k")
    parser.add_argument("--other", default="uffizi_256")
    parser.add_argument("--by-input", action="store_true", help="the per-input table of results.md's training section")
    args = parser.parse_args()
    records = {}
    for folder in args.folders:
        found = load(folder)
        for name in sorted(set(found) & set(records)):
            print(f"note: {name} is in more than one folder; {folder}'s record is used", file=sys.stderr)
        records.update(found)
    both = f"{args.single}+{args.other}"
    if args.by_input:
        by_input(records, args.single, args.other)
        return
    rows = []
    for name, r in sorted(records.items()):
        e = r["inputs"]
        exact = r["floors"]["exact_floor"]
        confident, nan = e[args.single].get("confident", {}), float("nan")
        row = {"material": name, "ratio 1 image": ratio(e[args.single]),
               "eq1 observed / exact floor": e[args.single]["recovered"]["eq1_observed"] / exact,
               "grid floor observed / exact floor": e[args.single]["grid_floor_observed"] / exact,
               # the exact floor over the same observed cells (records before stop 25 lack it: NaN)
               "eq1 observed / exact floor there": e[args.single]["recovered"]["eq1_observed"]
               / e[args.single].get("exact_floor_observed", nan),
               # older records (before the confidence was scored) have no "confident" entry: NaN
               "confident cells (share)": confident.get("node_fraction", nan),
               "eq1 confident / exact floor": confident.get("eq1", nan) / exact,
               "eq1 confident / grid floor there": confident.get("eq1", nan) / confident.get("floor_eq1", nan),
               "eq1 confident / exact floor there": confident.get("eq1", nan) / confident.get("exact_floor_eq1", nan),
               "eq1 f>1e-3 / exact floor (f>1e-3)": e[args.single]["recovered"]["eq1_min"] / r["floors"]["exact_floor_min"],
               "grid floor f>1e-3 / exact floor (f>1e-3)": r["floors"]["grid_floor_min"] / r["floors"]["exact_floor_min"]}
        if both in e:
            row["ratio 2 images"] = ratio(e[both])
            row["2 images beat the better single"] = relight(e[both]) < min(relight(e[args.single]), relight(e[args.other]))
        rows.append(row)
    keys = list(rows[0])
    print("| " + " | ".join(keys) + " |\n|" + "---|" * len(keys))
    for row in rows:
        print("| " + " | ".join(f"{v:.2f}" if isinstance(v, float) else str(v) for v in row.values()) + " |")
    print(f"\n{len(rows)} materials. Medians:")
    for k in keys[1:]:
        values = [row[k] for row in rows if k in row]
        if values and isinstance(values[0], bool):
            print(f"- {k}: {sum(values)}/{len(values)} ({100 * np.mean(values):.0f}%)")
        elif values:
            print(f"- {k}: {np.nanmedian(values):.2f}" if not np.all(np.isnan(values)) else f"- {k}: n/a")
    if args.noisy:
        noisy = load(args.noisy)
        names = [m for m in sorted(noisy) if m in records]
        pairs = [(relight(noisy[m]["inputs"][args.single]), relight(records[m]["inputs"][args.single])) for m in names]
        print("\n| material | relight error, clean | with input noise | noisy / clean |\n|---|---|---|---|")
        for m, (a, b) in zip(names, pairs):
            print(f"| {m} | {b:.4f} | {a:.4f} | {a / b:.2f} |")
        print(f"- noisy / clean relight error ({len(pairs)} materials): median "
              f"{np.median([a / b for a, b in pairs]):.2f}; medians {np.median([a for a, _ in pairs]):.4f} / "
              f"{np.median([b for _, b in pairs]):.4f}")


if __name__ == "__main__":
    main()
