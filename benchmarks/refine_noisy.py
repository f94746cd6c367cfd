"""`recover --refine-sphere` on a noisy photo: 96 px, 32 spp, path traced under grace_latlong_1k.

For each material the sphere is recovered four ways: under the exact sphere; under the sphere the
silhouette fit finds; refined as ``recover --refine-sphere`` runs it (the objective with the first
recovery's camera-noise model, and the second guard); refined with the model error alone and no
second guard (the objective before 2026-12-05, late). Every recovery uses leave-one-out priors and
is relit under pisa_256 by the reference quadrature (128 px). The script prints each sphere's centre
and radius errors (px), the recovery's relative residual and its relight error, and the scoring
renders' own noise (the truth's and the refined table's, each against its render at a second seed,
over sqrt 2) (docs/recovery.md section 9).

    MI_BIVARIATE_DATA=/work/shared/data OPENBLAS_NUM_THREADS=1 python benchmarks/refine_noisy.py
"""

from __future__ import annotations

import argparse
import warnings
from typing import Sequence

import numpy as np

from _machine import machine  # benchmarks/_machine.py

MATERIALS = ("gold-metallic-paint3", "red-phenolic", "nickel")


def main(argv: Sequence[str] = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--materials", nargs="+", default=list(MATERIALS))
    args = parser.parse_args(argv)

    from mi_bivariate import metrics, nbrdf, probes, reference, render, sphere_refine, spherefit, training_set
    from mi_bivariate.recover import recover, refine_sphere_and_recover
    from mi_bivariate.variants import ensure_variant

    ensure_variant()
    warnings.simplefilter("ignore")
    print(f"Machine: {machine()}\n")
    print("| material | sphere | centre error (px) | radius error (px) | relative residual | relight error |")
    print("|---|---|---:|---:|---:|---:|")
    grace, pisa = probes.shared_probe("grace_latlong_1k"), probes.shared_probe("pisa_256")
    refine = sphere_refine.refine_sphere
    for material in args.materials:
        truth = nbrdf.nbrdf_merl(material)
        priors = dict(zip(("prior", "basis_prior"), training_set.leave_one_out_priors(material)))
        shot = render.render_sphere(render.bsdf_dict(truth), grace, resolution=96, spp=32, seed=0)
        want = reference.render_reference(truth, pisa, resolution=128, seed=1)
        first = recover(shot.image, grace, spherefit.fit_sphere(shot.image, warn=False).geometry, seed=0, **priors)
        runs = {"exact": recover(shot.image, grace, shot.geometry, seed=0, **priors), "fitted": first,
                "refined (now)": refine_sphere_and_recover(shot.image, grace, first, seed=0, **priors)}
        saved = sphere_refine.MAX_RESIDUAL_RISE
        sphere_refine.refine_sphere = lambda *a, **k: refine(*a, **{**k, "noise": None})
        sphere_refine.MAX_RESIDUAL_RISE = np.inf
        try:
            runs["refined, model error only, no second guard"] = refine_sphere_and_recover(
                shot.image, grace, first, seed=0, **priors)
        finally:
            sphere_refine.refine_sphere, sphere_refine.MAX_RESIDUAL_RISE = refine, saved
        for name, result in runs.items():
            g, g0 = result.geometries[0], shot.geometry
            got = reference.render_reference(result.brdf, pisa, resolution=128, seed=1)
            relight = metrics.image_relative_rmse(got.image, want.image, want.mask)
            print(f"| {material} | {name} | {np.hypot(g.cx - g0.cx, g.cy - g0.cy):.3f} | {g.radius - g0.radius:+.3f} "
                  f"| {result.relative_residual():.4f} | {relight:.4f} |", flush=True)
        noise = [metrics.image_relative_rmse(reference.render_reference(brdf, pisa, resolution=128, seed=2).image,
                                             first_render.image, want.mask) / np.sqrt(2.0)
                 for brdf, first_render in ((truth, want), (runs["refined (now)"].brdf, reference.render_reference(
                     runs["refined (now)"].brdf, pisa, resolution=128, seed=1)))]
        print(f"| {material} | own noise of the scoring renders (seeds 1, 2; / sqrt 2) | | | truth {noise[0]:.5f} "
              f"| refined table {noise[1]:.5f} |", flush=True)


if __name__ == "__main__":
    main()
