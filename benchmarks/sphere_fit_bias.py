"""The automatic sphere fit on glossy spheres: its bias, and what the bias costs a recovery.

For each material and input probe, a sphere rendered at 128 and 256 px (64 spp, black
background, the geometry known exactly) is fitted by :func:`mi_bivariate.spherefit.fit_sphere`
with the default coverage refinement (``REFINE_PASSES`` = 2) and with the crack points of the
thresholded region alone (0 passes). The script prints the centre and radius errors (pixels). With
``--relight``, the 256 px sphere under grace_latlong_1k is also recovered with the exact and the
two fitted geometries, each table is rendered under pisa_256 by the converged reference
quadrature (128 px), and the relight error is printed beside the recovery's relative residual.

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
RELIGHT_MATERIALS = ("gold-metallic-paint3", "red-phenolic", "nickel", "yellow-matte-plastic")


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
    args = parser.parse_args(argv)

    from mi_bivariate import metrics, nbrdf, probes, reference, render
    from mi_bivariate.recover import recover
    from mi_bivariate.variants import ensure_variant

    ensure_variant()
    warnings.simplefilter("ignore")
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
    grace, pisa = probes.shared_probe("grace_latlong_1k"), probes.shared_probe("pisa_256")
    print("\n| material | geometry | centre error | radius error | relative residual | relight error (pisa_256) |")
    print("|---|---|---:|---:|---:|---:|")
    for material in RELIGHT_MATERIALS:
        truth = nbrdf.nbrdf_merl(material)
        shot = render.render_sphere(render.bsdf_dict(truth), grace, resolution=256, spp=64, seed=0)
        want = reference.render_reference(truth, pisa, resolution=128, seed=1)
        candidates = [("exact", 0.0, 0.0, shot.geometry)]
        for passes in (2, 0):
            dc, dr, geometry = fit_errors(shot.image, shot.geometry, passes)
            candidates.append((f"fitted, {passes} passes", dc, dr, geometry))
        for name, dc, dr, geometry in candidates:
            result = recover(shot.image, grace, geometry, seed=0)
            got = reference.render_reference(result.brdf, pisa, resolution=128, seed=1)
            relight = metrics.image_relative_rmse(got.image, want.image, want.mask)
            print(f"| {material} | {name} | {dc:.2f} | {dr:+.2f} | {result.relative_residual():.4f} | {relight:.4f} |",
                  flush=True)


if __name__ == "__main__":
    main()
