"""The automatic sphere fit on glossy spheres: its bias, and what the bias costs a recovery.

For each material and input probe, a sphere rendered at 128 and 256 px (64 spp, black
background, the geometry known exactly) is fitted by :func:`mi_bivariate.spherefit.fit_sphere`
with the default coverage refinement (``REFINE_PASSES`` = 2) and with the crack points of the
thresholded region alone (0 passes). The script prints the centre and radius errors (pixels). With
``--relight``, each 256 px sphere is also recovered with the exact geometry, the two fitted ones and
the default fit refined by shading (:func:`mi_bivariate.recover.refine_sphere_and_recover`, what
``recover --refine-sphere`` runs); each table is rendered under a novel probe (pisa_256 for the
grace_latlong_1k input, uffizi_256 for the pisa_256 input) by the converged reference quadrature
(128 px), and the relight error is printed beside the recovery's relative residual and the own
noise of the truth's and the refined table's renders (their images at a second seed). Every
recovery of a shared material uses priors learnt without it (leave-one-out, as the evaluation
does); ``--packaged-priors`` uses the packaged ones, which saw all 73 shared materials.

    MI_BIVARIATE_DATA=/work/shared/data python benchmarks/sphere_fit_bias.py [--relight]
"""

from __future__ import annotations

import argparse
import warnings
from typing import Sequence

import numpy as np

from _machine import machine  # benchmarks/_machine.py

MATERIALS = ("gold-metallic-paint3", "red-phenolic", "yellow-matte-plastic", "chrome-steel", "blue-acrylic",
             "brass", "black-fabric", "nickel")
PROBES = ("grace_latlong_1k", "pisa_256")


def fit_errors(image: np.ndarray, truth, passes: int):
    """``(centre error px, radius error px, geometry)`` of the fit with ``passes`` refinement passes."""
    from mi_bivariate import spherefit

    saved = spherefit.REFINE_PASSES
    spherefit.REFINE_PASSES = passes
    try:
        fit = spherefit.fit_sphere(image, warn=False)
    finally:
        spherefit.REFINE_PASSES = saved
    return float(np.hypot(fit.cx - truth.cx, fit.cy - truth.cy)), float(fit.radius - truth.radius), fit.geometry


def main(argv: Sequence[str] = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--materials", nargs="+", default=list(MATERIALS))
    parser.add_argument("--relight", action="store_true", help="also measure what the bias costs a recovery")
    parser.add_argument("--packaged-priors", action="store_true",
                        help="recover with the packaged priors (learnt on all 73 shared materials, these included) "
                             "instead of leave-one-out ones")
    parser.add_argument("--refine-without-noise", action="store_true",
                        help="refine with the model error alone in the objective (as before the objective took "
                             "the camera noise in), not the "
                             "first recovery's camera-noise model")
    args = parser.parse_args(argv)

    from mi_bivariate import metrics, nbrdf, probes, reference, render, training_set
    from mi_bivariate.recover import recover, refine_sphere_and_recover
    from mi_bivariate.variants import ensure_variant

    ensure_variant()
    warnings.simplefilter("ignore")
    if args.refine_without_noise:
        from mi_bivariate import sphere_refine

        refine = sphere_refine.refine_sphere
        sphere_refine.refine_sphere = lambda *a, **k: refine(*a, **{**k, "noise": None})
    print(f"Machine: {machine()}\n")
    print("| probe | material | px | centre error, 2 passes | radius error, 2 passes | centre error, 0 passes "
          "| radius error, 0 passes |")
    print("|---|---|---:|---:|---:|---:|---:|")
    errors = {2: [], 0: []}
    for probe_name in PROBES:
        probe = probes.shared_probe(probe_name)
        for material in args.materials:
            truth = nbrdf.nbrdf_merl(material)
            for resolution, seed in ((128, 1), (256, 0)):
                shot = render.render_sphere(render.bsdf_dict(truth), probe, resolution=resolution, spp=64, seed=seed)
                cells = []
                for passes in (2, 0):
                    dc, dr, _ = fit_errors(shot.image, shot.geometry, passes)
                    errors[passes].append((dc, dr))
                    cells += [f"{dc:.3f}", f"{dr:+.3f}"]
                print(f"| {probe_name} | {material} | {resolution} | " + " | ".join(cells) + " |", flush=True)
    for passes, e in errors.items():
        e = np.array(e)
        print(f"\n{passes} passes: centre error median {np.median(e[:, 0]):.3f} px, max {e[:, 0].max():.3f}; "
              f"|radius error| median {np.median(np.abs(e[:, 1])):.3f} px, max {np.abs(e[:, 1]).max():.3f}")

    if not args.relight:
        return
    print(f"\npriors: {'packaged (73 shared materials)' if args.packaged_priors else 'leave-one-out (72 materials)'}")
    print("\n| input probe | material | geometry | centre error | radius error | relative residual "
          "| relight error | / exact geometry's |")
    print("|---|---|---|---:|---:|---:|---:|---:|")
    ratios = {"fitted, 2 passes": [], "fitted, 0 passes": [], "refined": []}
    for probe_name, novel_name in (("grace_latlong_1k", "pisa_256"), ("pisa_256", "uffizi_256")):
        probe, novel = probes.shared_probe(probe_name), probes.shared_probe(novel_name)
        for material in args.materials:
            truth = nbrdf.nbrdf_merl(material)
            priors = {} if args.packaged_priors else dict(zip(
                ("prior", "basis_prior"), training_set.leave_one_out_priors(material)))
            shot = render.render_sphere(render.bsdf_dict(truth), probe, resolution=256, spp=64, seed=0)
            want = reference.render_reference(truth, novel, resolution=128, seed=1)
            runs = [("exact", recover(shot.image, probe, shot.geometry, seed=0, **priors))]
            for passes in (2, 0):
                runs.append((f"fitted, {passes} passes",
                             recover(shot.image, probe, fit_errors(shot.image, shot.geometry, passes)[2], seed=0,
                                     **priors)))
            refined = refine_sphere_and_recover(shot.image, probe, runs[1][1], seed=0, **priors)
            refinement = refined.sphere_refinement
            label = (f"refined ({refinement.evaluations} evaluations, {refinement.seconds:.1f} s)"
                     if refinement.accepted else
                     f"refined (not taken: {refinement.shift_px:.2f} px away; {refinement.seconds:.1f} s)")
            runs.append((label, refined))
            exact = None
            for name, result in runs:
                geometry = result.geometries[0]
                dc = float(np.hypot(geometry.cx - shot.geometry.cx, geometry.cy - shot.geometry.cy))
                dr = float(geometry.radius - shot.geometry.radius)
                got = reference.render_reference(result.brdf, novel, resolution=128, seed=1)
                relight = metrics.image_relative_rmse(got.image, want.image, want.mask)
                exact = relight if exact is None else exact
                if name.split(" (")[0] in ratios:
                    ratios[name.split(" (")[0]].append(relight / exact)
                print(f"| {probe_name} | {material} | {name} | {dc:.3f} | {dr:+.3f} | {result.relative_residual():.4f} "
                      f"| {relight:.4f} | {relight / exact:.3f} |", flush=True)
            # The scoring renders' own noise: the truth's and the last (refined) table's, at another seed.
            noise = [metrics.image_relative_rmse(a.image, reference.render_reference(b, novel, resolution=128,
                                                                                     seed=2).image, a.mask)
                     / np.sqrt(2.0) for a, b in ((want, truth), (got, result.brdf))]
            print(f"| {probe_name} | {material} | own noise of the scoring renders (seeds 1, 2; / sqrt 2) | | | | "
                  f"truth {noise[0]:.5f} | refined table {noise[1]:.5f} |", flush=True)
    print("\nmedian relight error / the exact geometry's: " + ", ".join(
        f"{name} {np.median(r):.3f} (max {np.max(r):.3f})" for name, r in ratios.items()))


if __name__ == "__main__":
    main()
