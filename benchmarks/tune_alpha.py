"""Choose the one regularisation weight alpha used for every material (paper, Sect. 4).

For each shared MERL-NBRDF material: render the input sphere under the input
probe with the `merl` plugin (the full 3D table), build the lighting matrix,
and solve Eq. 6 for a range of alphas (normal equations built once). Each
alpha is scored by

- the Eq. 1 error of the recovered table against the 3D truth, divided by the
  material's bivariate floor (the reduction error), and
- a novel-lighting error: the lighting matrix of a second probe at the same
  normals applied to the recovered table, against the same matrix applied to
  the bivariate truth (relative RMS over pixels and channels).

Run (about 15 minutes on 2 cores with the defaults; renders are cached):

    MI_BIVARIATE_DATA=../shared/data OPENBLAS_NUM_THREADS=1 \\
        .venv/bin/python benchmarks/tune_alpha.py --cache out/tune_alpha

It prints one Markdown table per alpha summary and the per-material numbers
at the chosen alpha.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from mi_bivariate import capture, lighting, nbrdf, probes, render
from mi_bivariate.bivariate import BivariateBRDF, reduction_error
from mi_bivariate.geometry import SphereCamera
from mi_bivariate.metrics import image_relative_rmse
from mi_bivariate.prior import default_prior
from mi_bivariate.solve import prepare_data_term, solve_prepared
from mi_bivariate.variants import ensure_variant

ALPHAS = (1e-7, 3e-7, 1e-6, 3e-6, 1e-5, 3e-5, 1e-4, 3e-4, 1e-3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--materials", nargs="*", default=list(nbrdf.NBRDF_MATERIALS))
    parser.add_argument("--input-probe", default="grace_latlong_1k")
    parser.add_argument("--novel-probe", default="pisa_256")
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--spp", type=int, default=256)
    parser.add_argument("--cache", default="out/tune_alpha")
    parser.add_argument("--alphas", type=float, nargs="*", default=list(ALPHAS))
    parser.add_argument("--render-novel", action="store_true",
                        help="also re-render each recovery and its 3D truth under the novel probe "
                             "(same seed, 128 px, 256 spp) and report the image relative RMSE")
    args = parser.parse_args()

    ensure_variant()
    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    probe_in = probes.shared_probe(args.input_probe)
    probe_novel = probes.shared_probe(args.novel_probe)
    prior = default_prior()
    results = {}
    for name in args.materials:
        t0 = time.perf_counter()
        truth = nbrdf.nbrdf_merl(name)
        floor = BivariateBRDF.reduce(truth)
        shot_file = cache / f"{name}_{args.input_probe}_{args.resolution}_{args.spp}.npz"
        if shot_file.exists():
            with np.load(shot_file) as z:
                image = z["image"]
            geometry = SphereCamera.create("orthographic", args.resolution).sphere_geometry(0.45)
        else:
            shot = render.render_sphere(render.bsdf_dict(truth), probe_in, resolution=args.resolution,
                                        spp=args.spp, seed=0)
            image, geometry = shot.image, shot.geometry
            np.savez_compressed(shot_file, image=image)
        obs = capture.observations_from_sphere(image, geometry, seed=0)
        L = lighting.lighting_matrix(obs, [probe_in], progress=False)
        L_novel = lighting.lighting_matrix(obs, [probe_novel], progress=False)
        data = prepare_data_term(L, obs.values)
        f_floor = floor.table.reshape(-1, 3).astype(np.float64)
        ref = np.einsum("mnc,nc->mc", L_novel, f_floor)
        floor_err = reduction_error(truth, floor)
        rows = []
        for alpha in args.alphas:
            sol = solve_prepared(data, prior, alpha)
            rec = BivariateBRDF(sol.table)
            pred = np.einsum("mnc,nc->mc", L_novel, sol.table.reshape(-1, 3).astype(np.float64))
            row = {
                "alpha": alpha,
                "eq1": reduction_error(truth, rec),
                "eq1_f>1e-3": reduction_error(truth, rec, min_value=1e-3),
                "novel": float(np.linalg.norm(pred - ref) / np.linalg.norm(ref)),
                "winner": "/".join(sol.winner),
            }
            if args.render_novel:
                want = render.render_sphere(render.bsdf_dict(truth), probe_novel, resolution=128, spp=256, seed=1)
                got = render.render_sphere(render.bsdf_dict(rec), probe_novel, resolution=128, spp=256, seed=1)
                row["image_rmse"] = image_relative_rmse(got.image, want.image, want.mask)
            rows.append(row)
        results[name] = {"floor": floor_err, "floor_f>1e-3": reduction_error(truth, floor, min_value=1e-3),
                         "rows": rows}
        best = min(rows, key=lambda r: r["eq1"])
        print(f"{name:26s} floor {floor_err:7.3f}  best eq1 {best['eq1']:7.3f} at {best['alpha']:.0e}  "
              f"({time.perf_counter() - t0:.0f} s)", flush=True)
    (cache / "results.json").write_text(json.dumps(results, indent=1))

    if len(args.alphas) == 1:
        print("\n| material | Eq. 1 floor | Eq. 1 recovered | ratio | ratio (f > 1e-3) | novel (L) |"
              + (" novel image |" if args.render_novel else ""))
        print("|---|---|---|---|---|---|" + ("---|" if args.render_novel else ""))
        for name, r in results.items():
            row = r["rows"][0]
            line = (f"| {name} | {r['floor']:.3f} | {row['eq1']:.3f} | {row['eq1'] / r['floor']:.2f} | "
                    f"{row['eq1_f>1e-3'] / r['floor_f>1e-3']:.2f} | {row['novel']:.4f} |")
            print(line + (f" {row['image_rmse']:.4f} |" if args.render_novel else ""))

    print("\n| alpha | median Eq.1 / floor | share <= 3x floor | same, f > 1e-3 | median novel-light error "
          "| share < 5% |" + (" share of images < 5% |" if args.render_novel else ""))
    print("|---|---|---|---|---|---|" + ("---|" if args.render_novel else ""))
    for k, alpha in enumerate(args.alphas):
        ratio = np.array([r["rows"][k]["eq1"] / r["floor"] for r in results.values()])
        ratio_f = np.array([r["rows"][k]["eq1_f>1e-3"] / r["floor_f>1e-3"] for r in results.values()])
        novel = np.array([r["rows"][k]["novel"] for r in results.values()])
        line = (f"| {alpha:.0e} | {np.median(ratio):.2f} | {np.mean(ratio <= 3):.2f} | {np.mean(ratio_f <= 3):.2f} | "
                f"{np.median(novel):.4f} | {np.mean(novel < 0.05):.2f} |")
        if args.render_novel:
            images = np.array([r["rows"][k]["image_rmse"] for r in results.values()])
            line += f" {np.mean(images < 0.05):.2f} |"
        print(line)


if __name__ == "__main__":
    main()
