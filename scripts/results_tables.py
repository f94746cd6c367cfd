"""The generated part of docs/results.md, from one evaluation folder.

Usage:
    python scripts/results_tables.py [OUT_DIR] [--page docs/results.md] [--figures docs/figures]

Prints the Markdown (per-material table, medians, relighting per novel probe, baselines, timing)
for the records of OUT_DIR's configuration (default out/evaluate). With ``--page`` it replaces
the text between ``<!-- results:begin -->`` and ``<!-- results:end -->`` in that page
(atomically); with ``--figures`` it draws the evaluation figures into that folder.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from mi_bivariate import evaluate as ev
from mi_bivariate.adequacy import OBSERVED_MIN_EFFECTIVE, OBSERVED_MIN_SIGNAL
from mi_bivariate.atomic import atomic_path
from mi_bivariate.evaluate.results import _fmt

BEGIN, END = "<!-- results:begin -->", "<!-- results:end -->"
METRICS = (("eq1", "Eq. 1, all cells"), ("eq1_observed", "Eq. 1, observed cells"),
           ("eq1_min", "Eq. 1, f > 1e-3"), ("cosine", "cosine-weighted"), ("log", "log-space"))


def _median(values) -> float:
    v = [x for x in values if isinstance(x, (int, float)) and math.isfinite(x)]
    return float(np.median(v)) if v else float("nan")


def _f(v: float) -> str:
    return _fmt(v)


def generate(out: Path) -> str:
    config = json.loads((out / "config.json").read_text())
    h = config["config_hash"]
    recs = ev.read_records(out / ev.RESULTS_FILE, h)
    if not recs:
        raise SystemExit(f"no records of configuration {h} in {out / ev.RESULTS_FILE}")
    rows = ev.summary_rows(recs)
    probes = list(dict.fromkeys(r["input_probe"] for r in rows))
    novels = list(recs[0]["floor_images"])
    lines = [f"Configuration `{h}`: {len(recs)} materials x {len(probes)} input probes; renderer "
             f"`{config.get('renderer', 'path')}`, input {config['resolution']} px, novel-probe renders "
             f"{config.get('novel_resolution', config['resolution'])} px, grid {config['grid'][0]} x "
             f"{config['grid'][1]}, input noise {config.get('noise', 0.0)}. "
             f"Observed nodes: >= {OBSERVED_MIN_EFFECTIVE:g} effective rows and >= {OBSERVED_MIN_SIGNAL:g} "
             "pixels' worth of signal.", ""]

    lines += ["### Medians over materials", "",
              "| input probe | exact floor | grid floor | rec. Eq. 1 | rec. Eq. 1 observed | exact floor observed "
              "| grid floor observed | observed cells | rec. Eq. 1 confident | exact floor confident "
              "| grid floor confident | confident cells "
              "| rec. Eq. 1 > 1e-3 | rec. cosine | rec. log | relight | relight floor | ratio |",
              "|---|" + "---:|" * 17]
    for p in probes:
        sel = [r for r in rows if r["input_probe"] == p]
        keys = ("exact_floor", "grid_floor", "recovered_eq1", "recovered_eq1_observed", "exact_floor_observed",
                "grid_floor_observed", "observed_fraction", "recovered_eq1_confident", "exact_floor_confident",
                "grid_floor_confident", "confident_fraction",
                "recovered_eq1_min", "recovered_cosine", "recovered_log",
                "relight_rmse_median", "relight_floor_median", "relight_ratio_median")
        lines.append(f"| {p} | " + " | ".join(_f(_median(r.get(k) for r in sel)) for k in keys) + " |")

    lines += ["", "### Relighting under each novel probe (median relative RMSE: recovered / relight floor / "
              "ratio)", "", "| input probe | " + " | ".join(novels) + " |", "|---|" + "---:|" * len(novels)]
    for p in probes:
        cells = []
        for n in novels:
            e = [r["inputs"][p]["images"][n] for r in recs if p in r["inputs"]]
            cells.append(f"{_f(_median(x['rel_rmse'] for x in e))} / {_f(_median(x.get('floor') for x in e))} / "
                         f"{_f(_median(x.get('ratio') for x in e))}")
        lines.append(f"| {p} | " + " | ".join(cells) + " |")

    lines += ["", "### Reference noise (the truth's renders under each novel probe: two seeds' relative RMS "
              "difference / sqrt 2, per record)", ""]
    if all(r.get("reference_noise") for r in recs):
        lines += ["| novel probe | median | largest (material) | noise / the material's relight floor, largest "
                  "| noise / its recovered relight error (any input), largest |", "|---|---:|---:|---:|---:|"]
        for n in novels:
            # a black truth render has no relative noise (null in the record): such records are left out
            kept = [r for r in recs if isinstance(r["reference_noise"].get(n), float)
                    and math.isfinite(r["reference_noise"][n])]
            if not kept:
                lines.append(f"| {n} | - | - | - | - |")
                continue
            noise = {r["material"]: r["reference_noise"][n] for r in kept}
            worst = max(noise, key=noise.get)
            to_floor = max((r["reference_noise"][n] / r["relight_floor"][n] for r in kept
                            if r["relight_floor"].get(n)), default=float("nan"))
            errors = [(r, min(e["images"][n]["rel_rmse"] for e in r["inputs"].values())) for r in kept]
            to_error = max((r["reference_noise"][n] / e for r, e in errors if e), default=float("nan"))
            lines.append(f"| {n} | {_f(_median(noise.values()))} | {_f(noise[worst])} ({worst}) | {_f(to_floor)} "
                         f"| {_f(to_error)} |")
    else:
        lines.append("Not measured in these records (written before each record measured it).")

    lines += ["", "### Where Eq. 1 comes from (recovered; median over materials: Eq. 1 of the region / share "
              "of the summed squared relative error)", "",
              "| input probe | specular (theta_h < 2 deg) | retro (theta_d < 10 deg) | grazing (theta_d > 75 deg) "
              "| rest |", "|---|---:|---:|---:|---:|"]
    for p in probes:
        sel = [r for r in rows if r["input_probe"] == p]
        lines.append(f"| {p} | " + " | ".join(
            f"{_f(_median(r.get(f'recovered_eq1_{g}') for r in sel))} / "
            f"{_f(_median(r.get(f'recovered_share_{g}') for r in sel))}"
            for g in ("specular", "retro", "grazing", "rest")) + " |")

    lines += ["", "### Baselines (median over materials; the same observations and lighting matrix)", "",
              "| input probe | metric | grid floor | recovered | GGX fit (3D) | Ward fit (3D) |",
              "|---|---|---:|---:|---:|---:|"]
    for p in probes:
        for m, name in METRICS:
            e = [r["inputs"][p] for r in recs if p in r["inputs"]]
            floor = _median(r["floor"].get(m) for r in recs) if m != "eq1_observed" else \
                _median(x.get("grid_floor_observed") for x in e)
            lines.append(f"| {p} | {name} | {_f(floor)} | {_f(_median(x['recovered'].get(m) for x in e))} | "
                         + " | ".join(_f(_median(x.get("baselines", {}).get(fam, {}).get("errors", {}).get(m)
                                                 for x in e)) for fam in ("ggx", "ward")) + " |")

    lines += ["", "### Per material", "", ev.markdown_table(recs, ev.HEADLINE_COLUMNS), ""]

    lines += ["### Time (seconds per material, mean over materials; wall time of one worker)", "",
              "| stage | s | share |", "|---|---:|---:|"]
    tot = {}
    for r in recs:
        for k, v in r["timings"].items():
            if k not in ("total", "cpu_total", "render_seconds", "renders_rendered", "renders_from_cache"):
                tot[f"(material) {k}"] = tot.get(f"(material) {k}", 0.0) + v
        for e in r["inputs"].values():
            for k, v in e["timings"].items():
                tot[k] = tot.get(k, 0.0) + v
    s = sum(tot.values())
    for k, v in sorted(tot.items(), key=lambda x: -x[1]):
        lines.append(f"| {k} | {v / len(recs):.1f} | {100 * v / s:.0f}% |")
    rendered = sum(r["timings"].get("renders_rendered", 0) for r in recs)
    cached = sum(r["timings"].get("renders_from_cache", 0) for r in recs)
    cpu = _median(r["timings"].get("cpu_total") for r in recs)
    lines += ["", f"Mean total per material {np.mean([r['timings']['total'] for r in recs]):.1f} s wall, "
              f"median {cpu:.1f} CPU-s; "
              f"reference renders {rendered:.0f} rendered, {cached:.0f} from the cache, "
              f"{np.mean([r['timings'].get('render_seconds', 0.0) for r in recs]):.1f} s of rendering per "
              "material."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", nargs="?", default="out/evaluate", help="evaluation folder")
    parser.add_argument("--page", default=None, help="Markdown page whose marked section is replaced")
    parser.add_argument("--figures", default=None, help="draw the figures into this folder")
    args = parser.parse_args(argv)
    out = Path(args.out)
    text = generate(out)
    if args.page:
        page = Path(args.page)
        old = page.read_text()
        if BEGIN not in old or END not in old:
            raise SystemExit(f"{page}: no {BEGIN} ... {END} section to replace")
        head, rest = old.split(BEGIN, 1)
        _, tail = rest.split(END, 1)
        with atomic_path(page) as tmp:
            tmp.write_text(head + BEGIN + "\n" + text + END + tail)
    if args.figures:
        ev.make_figures(out, fig_dir=args.figures, dpi=100)
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
