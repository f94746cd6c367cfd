"""Measure the quadrature error of the reference renderer (mi_bivariate.reference).

    python scripts/reference_noise.py [RESOLUTION] [FACTOR] [MATERIALS] [PROBES]
(defaults 64, 1, the six materials and three probes below)

MATERIALS, PROBES: comma-separated MERL-NBRDF and shared probe names.

For each material x probe: relative RMS difference of two seeds / sqrt 2 over the sphere
(``seed``), the difference against a render with 4x the directions (``vs 4x``), and the
CPU and wall seconds per render (one Dr.Jit thread). Directions = FACTOR x reference.DEFAULT_DIRECTIONS.
"""
import argparse

import drjit as dr

from mi_bivariate import evaluate as ev
from mi_bivariate import nbrdf, reference
from mi_bivariate.variants import ensure_variant

MATERIALS = ("blue-acrylic", "gold-metallic-paint3", "specular-white-phenolic", "tungsten-carbide",
             "brass", "hematite")
PROBES = ("grace_latlong_1k", "pisa_256", "pedestrian_overpass_1k")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("resolution", nargs="?", type=int, default=64, help="sphere image size (default: 64)")
    parser.add_argument("factor", nargs="?", type=float, default=1.0,
                        help="directions, times reference.DEFAULT_DIRECTIONS (default: 1)")
    parser.add_argument("materials", nargs="?", default=",".join(MATERIALS), help="comma-separated names")
    parser.add_argument("probes", nargs="?", default=",".join(PROBES), help="comma-separated shared probes")
    args = parser.parse_args()
    ensure_variant()
    dr.set_thread_count(1)
    dirs = reference.scaled_directions(args.factor)
    print(f"resolution {args.resolution}, directions {dirs} per pixel (cosine, lobe, environment)")
    print("| material | probe | seed noise | vs 4x | CPU s / render | wall s / render |")
    print("|---|---|---:|---:|---:|---:|")
    for name in args.materials.split(","):
        truth = nbrdf.nbrdf_merl(name)
        for probe in args.probes.split(","):
            q = reference.quadrature_noise(truth, ev.load_probe(probe), args.resolution, dirs, reference_factor=4.0)
            print(f"| {name} | {probe} | {q['seed_rms']:.4f} | {q['vs_large']:.4f} | {q['cpu_seconds']:.1f} | "
                  f"{q['seconds']:.1f} |", flush=True)


if __name__ == "__main__":
    main()
