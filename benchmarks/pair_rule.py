"""Which prior variant (weight pair) to keep per channel: the paper's residual rule against the evidence.

    MI_BIVARIATE_DATA=../shared/data OPENBLAS_NUM_THREADS=1 python benchmarks/pair_rule.py \
        --materials MATERIAL,... --out pair_rule.jsonl      # measure (append per material)
    python benchmarks/pair_rule.py --analyse pair_rule.jsonl [more.jsonl ...]   # the table

Row level, as benchmarks/ablation.py (2000 normals of a 128 px sphere, K = 8000 for the input,
relit under grace_256 / pisa_256 / pedestrian_overpass_1k through the MIS lighting matrix,
floor = the exact reduction through the same matrix, leave-one-out priors). For each input
(grace_latlong_1k, uffizi_256, both), the alpha the discrepancy principle chooses, and each
pair forced on every channel through both stages (as ``recover`` runs them), the script keeps
every channel's data term, prior term, ``log det(G + lambda P)`` and the relight errors per
channel, so that any per-channel rule is scored exactly afterwards: the residual rule (the
paper's), the evidence (:mod:`mi_bivariate.solve.evidence`, the default), the variants of it
that were tried, one pair for all channels, and the best choice in hindsight ("oracle").
Use training materials (``mi_bivariate.nbrdf.NBRDF_TRAIN_MATERIALS``) to choose.
"""

from __future__ import annotations

import argparse
import itertools
import json
import time

import numpy as np
from ablation import NOVEL, full_table, rel, render_rows

from mi_bivariate import capture, lighting, nbrdf, probes, solve, training_set
from mi_bivariate.geometry import SphereGeometry
from mi_bivariate.solve.common import penalty_weight
from mi_bivariate.solve.evidence import log_det_spd, penalty_log_pdet
from mi_bivariate.variants import ensure_variant

PAIRS = ("diffuse", "gloss")
INPUTS = {"G": ["grace_latlong_1k"], "U": ["uffizi_256"], "GU": ["grace_latlong_1k", "uffizi_256"]}


def measure(materials, out: str, normals: int = 2000) -> None:
    ensure_variant()
    obs = capture.image_observations(np.ones((128, 128, 3), np.float32), SphereGeometry(64, 64, 60),
                                     n_normals=normals, seed=0, saturation=2.0)
    inputs = {p: probes.shared_probe(p) for p in ("grace_latlong_1k", "uffizi_256")}
    novel = {p: probes.shared_probe(p) for p in NOVEL}
    L_in = {p: lighting.lighting_matrix(obs, inputs[p], n_dirs=8000) for p in inputs}
    L_novel = {p: lighting.lighting_matrix(obs, novel[p], n_dirs=32768, seed=5) for p in NOVEL}
    tables = training_set.reduced_tables(32, 32)
    for name in materials:
        t0 = time.perf_counter()
        prior, basis = training_set.learn_priors(tables, exclude=(name,))
        pen = {p: prior.penalty_matrix(p) for p in PAIRS}
        table3d = full_table(name)
        I = {p: render_rows(obs, inputs[p], table3d) for p in inputs}
        truth = {p: render_rows(obs, novel[p], table3d) for p in NOVEL}
        exact = tables[name].reshape(-1, 3)
        rec = {"material": name, "logpdet": {p: penalty_log_pdet(pen[p]) for p in PAIRS},
               "floors": {p: rel(np.einsum("mnc,nc->mc", L_novel[p], exact), truth[p]) for p in NOVEL},
               "truth2": {p: (truth[p].astype(np.float64) ** 2).sum(0).tolist() for p in NOVEL}, "cases": {}}
        for label, ps in INPUTS.items():
            L = np.concatenate([L_in[p] for p in ps])
            Iv = np.concatenate([I[p] for p in ps])
            data = solve.prepare_data_term(L, Iv, solve.row_sigma(Iv, np.repeat(np.arange(len(ps)), len(obs))))
            alphas = solve.solve_prepared(data, prior, "discrepancy", pairs=PAIRS[:1]).alphas
            case = {"alpha": float(alphas[0]), "M": int(data.n_rows)}
            for p in PAIRS:
                first = solve.solve_prepared(data, prior, alphas, pairs=(p,))
                mean, std = basis.predict(first.table, first.resolution, first.posterior_std)
                second = solve.solve_prepared(data, prior, alphas, mean=mean, mean_std=std, pairs=(p,))
                lam = [penalty_weight(float(alphas[k]), data.n_nodes, data.level[k]) for k in range(3)]
                f = second.table.reshape(-1, 3)
                case[p] = {"J1": first.pairs[p].data_term.tolist(), "R1": first.pairs[p].prior_term.tolist(),
                           "lam": lam, "ld1": [log_det_spd(data.gram[k] + lam[k] * pen[p]) for k in range(3)],
                           "err2": {q: ((np.einsum("mnc,nc->mc", L_novel[q], f) - truth[q]) ** 2).sum(0).tolist()
                                    for q in NOVEL}}
            rec["cases"][label] = case
        with open(out, "a") as fh:
            fh.write(json.dumps(rec) + "\n")
        print(f"{name} ({time.perf_counter() - t0:.0f} s)", flush=True)


def _ratio(rec: dict, case: str, choice) -> float:
    """Median over the novel probes of relight error / floor for one pair per channel."""
    out = []
    for q, floor in rec["floors"].items():
        e = sum(rec["cases"][case][choice[k]]["err2"][q][k] for k in range(3))
        out.append(np.sqrt(e / sum(rec["truth2"][q])) / floor)
    return float(np.median(out))


def _rules(rec: dict, case: str) -> dict:
    c = rec["cases"][case]
    m, a = c["M"], c["alpha"]

    def phi(p, k):
        return c[p]["J1"][k] + a * c[p]["R1"][k]

    def occam(p, k):
        log_pdet, rank = rec["logpdet"][p]
        return -0.5 * c[p]["ld1"][k] + 0.5 * (rank * np.log(c[p]["lam"][k]) + log_pdet)

    scales = {k: min(c[p]["J1"][k] for p in PAIRS) for k in range(3)}
    per_channel = {
        "residual (paper)": lambda k: min(PAIRS, key=lambda p: c[p]["J1"][k]),
        "evidence (default)": lambda k: max(PAIRS, key=lambda p: -0.5 * m * phi(p, k) + occam(p, k)),
        "evidence, noise scale from the fit": lambda k: max(PAIRS, key=lambda p: -0.5 * m * phi(p, k) / scales[k]
                                                            + occam(p, k)),
        "evidence, noise scale marginalised": lambda k: max(PAIRS, key=lambda p: -0.5 * m * np.log(phi(p, k))
                                                            + occam(p, k)),
        "lower objective (no Occam factor)": lambda k: min(PAIRS, key=lambda p: phi(p, k)),
    }
    out = {name: [rule(k) for k in range(3)] for name, rule in per_channel.items()}
    joint = min(PAIRS, key=lambda p: sum(c[p]["J1"]))
    out["residual, one pair for all channels"] = [joint] * 3
    out["diffuse always"], out["gloss always"] = ["diffuse"] * 3, ["gloss"] * 3
    return out


def analyse(files) -> None:
    recs = {}
    for f in files:
        for line in open(f):
            if line.strip():
                r = json.loads(line)
                recs[r["material"]] = r
    names = sorted(recs)
    scores = {}
    for name in names:
        for case in INPUTS:
            rules = _rules(recs[name], case)
            for rule, choice in rules.items():
                scores[(rule, name, case)] = _ratio(recs[name], case, choice)
            scores[("best in hindsight", name, case)] = min(
                _ratio(recs[name], case, ch) for ch in itertools.product(PAIRS, repeat=3))
    rules = list(dict.fromkeys(r for r, _, _ in scores))
    print(f"{len(names)} materials; median (geometric mean) over materials of relight / floor\n")
    print("| rule | grace | uffizi | grace + uffizi | two images beat the better single |\n|---|---|---|---|---|")
    for rule in rules:
        cells = []
        for case in INPUTS:
            v = np.array([scores[(rule, n, case)] for n in names])
            cells.append(f"{np.median(v):.2f} ({np.exp(np.mean(np.log(v))):.2f})")
        wins = sum(scores[(rule, n, "GU")] < min(scores[(rule, n, "G")], scores[(rule, n, "U")]) for n in names)
        print(f"| {rule} | " + " | ".join(cells) + f" | {wins}/{len(names)} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--materials", default=",".join(nbrdf.NBRDF_TRAIN_MATERIALS[8:]))
    parser.add_argument("--out", default="pair_rule.jsonl")
    parser.add_argument("--analyse", nargs="+", metavar="JSONL")
    args = parser.parse_args()
    if args.analyse:
        analyse(args.analyse)
    else:
        measure(args.materials.split(","), args.out)


if __name__ == "__main__":
    main()
